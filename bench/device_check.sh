#!/usr/bin/env bash
# One-GPU check of the paper-size work, under 8 minutes, with random weights (nothing downloaded):
#   1. a gsplat fit of the synthetic street's three front cameras at DriveStudio's 960x640
#      (bench/bench_gpu.py: fit iterations/s before and after densification starts, render fps,
#      peak GPU memory, the torch rasterizer as baseline);
#   2. the VAE encode of one 121 x 480 x 832 clip with Wan2.1's VAE configuration, bf16;
#   3. training steps of ReCamDriving stage 1 and stage 2 on the Wan2.1-T2V-1.3B configuration at
#      121 x 480 x 832 (62 latent frames, 96,720 tokens) with gradient checkpointing
#      (bench/bench_wan.py: steps/s and peak memory of each).
# Every part prints JSON; each runs under its own time limit so the whole stays under 8 minutes.
#
#   bench/device_check.sh          # on a machine with one CUDA GPU
#   bench/device_check.sh --cpu    # the same code at tiny sizes on the CPU (the tests run this)
#
# PY names the Python to use (default: .venv/bin/python of this checkout).
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
status=0

part() {   # part SECONDS COMMAND...: run one part under its limit; a failure or timeout is reported, the rest go on
    local limit=$1
    shift
    echo "== $*" >&2
    timeout --signal=TERM --kill-after=10 "$limit" "$@"
    local code=$?
    if [ "$code" -ne 0 ]; then
        echo "{\"part_failed\": \"$*\", \"exit\": $code}"
        status=1
    fi
}

if [ "${1:-}" = "--cpu" ]; then
    part 120 "$PY" bench/bench_gpu.py --device cpu --profile smoke --iterations 20 --baseline-iterations 5 \
        --frames 3 --width 96 --height 64
    part 120 "$PY" bench/bench_wan.py --device cpu --tiny --steps 2 --threads 1
else
    if ! "$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
        echo '{"device_check": "skipped", "why": "torch sees no CUDA GPU; bench/device_check.sh --cpu runs the tiny form"}'
        exit 0
    fi
    "$PY" -c "import torch; print({'gpu': torch.cuda.get_device_name(), 'torch': torch.__version__})" >&2
    part 170 "$PY" bench/bench_gpu.py --device cuda --iterations 600 --baseline-iterations 30 --frames 10
    part 80 "$PY" bench/bench_wan.py --device cuda --parts vae
    part 200 "$PY" bench/bench_wan.py --device cuda --parts train --stages 1,2 --steps 2
fi
exit $status
