# ParaDrive builder — one target per stage. Every target takes SCENE=, PROFILE=, DATA=, BUILD=.
SHELL := /bin/bash
PY ?= .venv/bin/python
PARADRIVE ?= .venv/bin/paradrive
SCENE ?= synthetic:demo?seed=7
PROFILE ?=
DATA ?= data
MANIFESTS ?= manifests
BUILD ?= default
PYTEST_ARGS ?=

profile_flag = $(if $(PROFILE),--profile $(PROFILE),)
build_args = --scene '$(SCENE)' $(profile_flag) --data $(DATA) --manifests $(MANIFESTS) --build $(BUILD)

.PHONY: setup setup-test setup-wan ingest fit render clip manifest build demo inspect eval status train train-wan encode lint test bench clean

# setup.py compiles the CPU kernels at install: an edited kernel source reinstalls
KERNEL_SOURCES = setup.py MANIFEST.in $(wildcard paradrive/kernels/*.cpp)
.venv/.installed: pyproject.toml scripts/setup.sh $(KERNEL_SOURCES)
	scripts/setup.sh build
	touch $@

.venv/.installed-test: pyproject.toml scripts/setup.sh $(KERNEL_SOURCES)
	scripts/setup.sh build,test
	touch $@ .venv/.installed .venv/.installed-wan

# the Wan2.1 commands (encode, train --model wan) need diffusers and transformers: the wan extra
.venv/.installed-wan: pyproject.toml scripts/setup.sh $(KERNEL_SOURCES)
	scripts/setup.sh build,wan
	touch $@ .venv/.installed

setup: .venv/.installed
setup-test: .venv/.installed-test
setup-wan: .venv/.installed-wan

ingest: setup
	$(PARADRIVE) build $(build_args) --stages ingest
fit: setup
	$(PARADRIVE) build $(build_args) --stages ingest,fit
render: setup
	$(PARADRIVE) build $(build_args) --stages ingest,fit,render
clip: setup
	$(PARADRIVE) build $(build_args) --stages ingest,fit,render,clip
manifest: setup
	$(PARADRIVE) build $(build_args)
build: setup
	$(PARADRIVE) build $(build_args)

# The embedded default: the synthetic street through every stage on a laptop, then a look at the result.
demo: PROFILE = demo
demo: setup
	$(PARADRIVE) build $(build_args)
	$(PARADRIVE) inspect $(MANIFESTS)/$(BUILD) --verify --sheet $(MANIFESTS)/$(BUILD)/contact_sheet.png

inspect: setup
	$(PARADRIVE) inspect $(MANIFESTS)/$(BUILD)
eval: setup
	$(PARADRIVE) eval --scene '$(SCENE)' $(profile_flag) --data $(DATA)
status: setup
	$(PARADRIVE) status $(MANIFESTS)/$(BUILD)

# The reference trainer on a build: stage 1, then stage 2 (TRAIN_CONFIG=smoke for a quick CPU run).
TRAIN_CONFIG ?= default
train: setup
	$(PARADRIVE) train --build $(MANIFESTS)/$(BUILD) --stage 1 --config $(TRAIN_CONFIG)
	$(PARADRIVE) train --build $(MANIFESTS)/$(BUILD) --stage 2 --config $(TRAIN_CONFIG)

# The build's Wan2.1 latent cache (<build>/latents/): WAN=<Wan2.1 diffusers folder> (its vae/,
# text_encoder/ and tokenizer/); ENCODE_ARGS=... passes more, e.g. --set encode.size=null.
ENCODE_ARGS ?=
encode: setup-wan
	$(PARADRIVE) encode $(MANIFESTS)/$(BUILD) --vae '$(WAN)' $(ENCODE_ARGS)

# ReCamDriving on Wan2.1, stage 1 then stage 2: WAN=<Wan2.1-T2V-1.3B diffusers folder> (its
# transformer/, vae/ and text_encoder/), or TRAIN_CONFIG=smoke for tiny random weights on a CPU.
WAN ?=
wan_flags = $(if $(WAN),--transformer $(WAN) --vae $(WAN) --text-encoder $(WAN),)
train-wan: setup-wan
	$(PARADRIVE) train --build $(MANIFESTS)/$(BUILD) --model wan --stage 1 --config $(TRAIN_CONFIG) $(wan_flags)
	$(PARADRIVE) train --build $(MANIFESTS)/$(BUILD) --model wan --stage 2 --config $(TRAIN_CONFIG) $(wan_flags)

# The lint and type gate first (ruff: style, one typing style, complexity limits; mypy on the
# package), then the suite.
lint: setup-test
	$(PY) -m ruff check paradrive tests bench
	$(PY) -m mypy

test: setup-test lint
	$(PY) -m pytest -q -n 2 --dist loadfile $(PYTEST_ARGS)

# Every benchmark (the nuScenes tables one alone takes about 15 minutes), or those BENCH names:
# make bench BENCH="bench/bench_fit.py bench/bench_rasterize.py"
# bench_scale.py runs at 50 scenes here; the paper's size is bench/README.md's command.
BENCH ?= $(wildcard bench/bench_*.py)
bench: setup-test
	@mkdir -p bench/results
	for b in $(BENCH); do echo "== $$b"; $(PY) $$b | tee bench/results/$$(basename $$b .py).json || exit 1; done

clean:
	rm -rf $(DATA) $(MANIFESTS)/*/ .pytest_cache
