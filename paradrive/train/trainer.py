"""The two-stage training loop: configs, data order, optimisation, checkpoints and exact resume.

A run lives in one folder (``<out>/stage<k>``)::

    config.yaml        the resolved config the run uses
    last.pt            the newest checkpoint (model, optimiser, EMA when on, data position, RNG states)
    ckpt_<step>.pt     checkpoints every ``train.checkpoint_every`` steps (``train.keep_last`` newest
                       kept, and every ``train.keep_every``-th step)
    metrics.jsonl      one line per step: step, loss, lr

Running again in the same folder resumes from ``last.pt`` and computes exactly what an
uninterrupted run would (fixed thread count, data order from (seed, epoch), saved RNG states).
Checkpoints hold tensors and plain data only (the config as parsed YAML, RNG states as byte
tensors) and are loaded without pickle: a file that needs it is refused.
"""

from __future__ import annotations

import contextlib
import copy
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterator, Mapping, Sequence

import torch
import yaml
from pydantic import ValidationError

from paradrive.data import PairDataset, epoch_order, per_rank, to_unit_range
from paradrive.devices import resolve_device
from paradrive.io import UnsafeFileError, atomic_path, load_tensors, stop_point, write_text
from paradrive.errors import ConfigError
from paradrive.contracts.specs import Param, coerce, default_stages_dir, yaml_value
from paradrive.train.autoencoder import VideoEncoder, make_autoencoder
from paradrive.train.distributed import all_agree, barrier, device_for, join, mean_over_ranks
from paradrive.train.flow import Generators, euler_sample, flow_matching_loss
from paradrive.train.model import ModelConfig, VideoDiT, is_stage2_parameter, load_stage1_weights

log = logging.getLogger(__name__)

CONFIG_DIR = default_stages_dir() / "train"
CHECKPOINT_FORMAT = "paradrive-train/2"


# -- configs -------------------------------------------------------------------------------------
# One config system with the stages: every setting of a base file is a ``Param`` ({default, doc}),
# an ``extends:`` file is a profile of plain values, and every override is type-checked against
# the setting's default as stage parameters are (paradrive.contracts.specs).

def _params(tree: Mapping[str, Any], where: str) -> dict:
    """{key: {default, doc}} leaves (nested in sections) -> {key: Param}."""
    out: dict = {}
    for key, node in tree.items():
        if isinstance(node, Mapping) and "doc" in node and "default" in node:
            try:
                out[key] = Param.model_validate(node)
            except ValidationError as exc:
                raise ConfigError(f"{where}.{key}: {exc.errors()[0]['msg']}") from exc
        elif isinstance(node, Mapping):
            out[key] = _params(node, f"{where}.{key}")
        else:
            raise ConfigError(f"{where}.{key}: write {{default: ..., doc: ...}}, got {node!r}")
    return out


def _defaults(params: Mapping[str, Any]) -> dict:
    return {k: (v.default if isinstance(v, Param) else _defaults(v)) for k, v in params.items()}


def _merge(values: dict, params: Mapping[str, Any], override: Mapping[str, Any], where: str) -> dict:
    out = copy.deepcopy(values)
    for key, value in override.items():
        if key not in params:
            raise ConfigError(f"{where}: unknown setting {key!r}; known: {', '.join(sorted(params))}")
        if isinstance(params[key], Param):
            out[key] = coerce(where.split(".", 1)[-1] or "train", key, params[key], value, where)
        elif not isinstance(value, Mapping):
            raise ConfigError(f"{where}.{key} is a section; give its settings, not {value!r}")
        else:
            out[key] = _merge(out[key], params[key], value, f"{where}.{key}")
    return out


def _load(path: Path) -> tuple[dict, dict]:
    """(the settings' Params, their values) of a config file, following ``extends``."""
    doc = yaml.safe_load(path.read_text()) or {}
    if doc.get("extends"):
        params, values = _load(path.parent / f"{doc['extends']}.yaml")
        return params, _merge(values, params, doc.get("params") or {}, path.name)
    params = _params(doc.get("params") or {}, path.name)
    return params, _defaults(params)


def load_config(source: str | Path | None = None, overrides: Mapping[str, Any] | None = None) -> dict:
    """Read a training config: a name in ``stages/train/`` (``default``, ``smoke``) or a YAML path.

    A base file declares every setting as ``{default: ..., doc: ...}``; a file that ``extends:``
    another lists only the values it changes. ``overrides`` (nested dict of plain values) are
    applied last. Unknown settings and values of the wrong type are ConfigErrors.
    """
    path = Path(source) if source is not None else CONFIG_DIR / "default.yaml"
    if not path.suffix and not path.exists():
        path = CONFIG_DIR / f"{path}.yaml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in CONFIG_DIR.glob("*.yaml")))
        raise FileNotFoundError(f"training config {source}: no such file (configs in {CONFIG_DIR}: {known})")
    params, values = _load(path)
    return _merge(values, params, overrides, "override") if overrides else values


def parse_set(items: Sequence[str]) -> dict:
    """``["model.dim=64", "train.lr=1e-3"]`` -> nested dict with YAML-parsed values."""
    out: dict = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set {item!r}: write section.key=value, e.g. model.dim=128")
        node = out
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
        try:
            node[leaf] = yaml_value(raw)
        except yaml.YAMLError as exc:   # a tag such as !!python/object is refused, never run
            problem = getattr(exc, "problem", None) or "unreadable"
            raise ValueError(f"--set {item!r}: the value is not plain YAML ({problem}); write a "
                             f"number, string, list or map, e.g. train.lr=3e-4 or data.height=48") from exc
    return out


# -- pieces built from a config -----------------------------------------------------------------
def build_model(config: Mapping[str, Any], stage: int, encoder: VideoEncoder) -> VideoDiT:
    m = config["model"]
    return VideoDiT(ModelConfig(latent_channels=encoder.latent_channels, dim=m["dim"], depth=m["depth"],
                                heads=m["heads"], mlp_ratio=m["mlp_ratio"], patch=m["patch"],
                                max_frames=m["max_frames"], rendering=stage == 2))


def open_dataset(build_dir: str | Path, config: Mapping[str, Any]):
    """The build's pairs through the adapter (``paradrive.data``), at the config's clip shape, as
    uint8 frames: a quarter of float32's bytes through the DataLoader, normalised on the device."""
    d = config["data"]
    return PairDataset(build_dir, num_frames=d["num_frames"], frame_stride=d["frame_stride"],
                       output_size=(d["height"], d["width"]), dtype="uint8")


def frames_on(frames: torch.Tensor, device: torch.device | str) -> torch.Tensor:
    """A batch's frames on ``device`` in [-1, 1]: uint8 frames (the adapter's ``dtype="uint8"``)
    travel as bytes and are normalised there; float frames are moved as they are."""
    if frames.dtype == torch.uint8:
        return to_unit_range(frames.to(device))
    return frames.to(device)


def _matches(name: str, modules: Sequence[str]) -> bool:
    return any(f".{m}." in f".{name}." for m in modules)


def trainable_mask(model: VideoDiT, stage: int, stage1_trainable: str | Sequence[str]) -> dict[str, bool]:
    """Which parameters a stage trains.

    Stage 2: only the Rendering / Cross Attention modules (everything from stage 1 frozen).
    Stage 1: ``all``, or a list of module names (the paper, starting from pretrained Wan2.1 and
    ReCamMaster weights, trains ``[self_attn, camera_encoder, frame_embed]``).
    """
    names = [n for n, _ in model.named_parameters()]
    if stage == 2:
        return {n: is_stage2_parameter(n) for n in names}
    if stage1_trainable == "all":
        return {n: True for n in names}
    if isinstance(stage1_trainable, str):
        stage1_trainable = [stage1_trainable]
    mask = {n: _matches(n, stage1_trainable) for n in names}
    if not any(mask.values()):
        raise ValueError(f"train.stage1_trainable={list(stage1_trainable)} names no parameter of the model")
    return mask


def latent_poses(poses: torch.Tensor, groups: Sequence[int]) -> torch.Tensor:
    """One pose per latent frame: poses (B, F, 4, 4) -> (B, f, 4, 4)."""
    if max(groups) >= poses.shape[1]:
        raise ValueError(f"the autoencoder wants the pose of frame {max(groups)}; the clip has {poses.shape[1]}")
    return poses[:, torch.as_tensor(list(groups), dtype=torch.long, device=poses.device)]


def collate(samples: list[dict]) -> dict:
    out = {}
    for key in samples[0]:
        values = [s[key] for s in samples]
        out[key] = torch.stack(values) if isinstance(values[0], torch.Tensor) else values
    return out


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run with ``n`` torch CPU threads (a fixed count makes a resumed run compute identically),
    then give the caller back its own."""
    before = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)


# -- checkpoints ---------------------------------------------------------------------------------
# what every checkpoint of a trainer holds (a file without one of them is damaged, not a resume point)
CHECKPOINT_KEYS = ("format", "stage", "step", "epoch", "batch_in_epoch", "world_size", "config", "model",
                   "optimizer", "torch_rng")
PREVIOUS = "previous.pt"


class DamagedCheckpoint(ValueError):
    """A checkpoint file that cannot be what it says: empty, truncated, overwritten, or missing a part."""


def read_checkpoint(path: str | Path, what: str, keys: Sequence[str] = CHECKPOINT_KEYS,
                    map_location: Any = "cpu") -> dict:
    """A trainer checkpoint's contents, loaded without pickle; :class:`DamagedCheckpoint` naming
    ``what`` (``--init x.pt``, the run's ``last.pt``) and what is wrong with it, in one line."""
    import zipfile

    path = Path(path)
    size = path.stat().st_size
    if size == 0:
        raise DamagedCheckpoint(f"{what} {path} is empty (0 bytes)")
    # torch writes a zip archive; anything else (a cut-off copy loses the zip's directory at its
    # end) is damage, not a file that needs pickle
    if not zipfile.is_zipfile(path):
        raise DamagedCheckpoint(f"{what} {path} is not a whole checkpoint ({size} bytes, not a torch "
                                f"archive: truncated or overwritten)")
    try:
        ckpt = load_tensors(path, map_location=map_location)
    except UnsafeFileError:
        raise
    except (RuntimeError, EOFError, OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DamagedCheckpoint(f"{what} {path} is damaged ({first})") from exc
    if not isinstance(ckpt, dict):
        raise DamagedCheckpoint(f"{what} {path} holds a {type(ckpt).__name__}, not a trainer checkpoint")
    missing = [k for k in keys if k not in ckpt]
    if missing:
        raise DamagedCheckpoint(f"{what} {path} lacks {', '.join(missing)}: not a whole trainer checkpoint")
    return ckpt


def scheduled_lr(train: Mapping[str, Any], step: int) -> float:
    """The learning rate of optimiser step ``step`` (0-based) under ``train``'s settings.

    Warm-up: ``lr * (step + 1) / warmup_steps`` for the first ``warmup_steps`` steps. After it,
    with p = (step - warmup_steps) / (steps - warmup_steps) held at 1 past the run's end:
    ``constant`` gives ``lr``; ``linear`` gives ``min_lr + (lr - min_lr) * (1 - p)``; ``cosine``
    gives ``min_lr + (lr - min_lr) * (1 + cos(pi * p)) / 2``. A function of the step alone, so a
    resumed run goes on with the schedule where it stopped.
    """
    lr, warmup, total = float(train["lr"]), int(train["warmup_steps"]), int(train["steps"])
    if step < warmup:
        return lr * (step + 1) / warmup
    kind = str(train["lr_schedule"])
    if kind == "constant":
        return lr
    low = float(train["min_lr"])
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    if kind == "linear":
        return low + (lr - low) * (1.0 - progress)
    if kind == "cosine":
        return low + (lr - low) * 0.5 * (1.0 + math.cos(math.pi * progress))
    raise ConfigError(f"train.lr_schedule = {kind!r}: use constant, cosine or linear")


def sample_seed(seed: int, stage: int, step: int, position: int) -> int:
    """The seed of one sample's flow noise and time: from the run's seed, the stage, the optimiser
    step and the sample's place in that step's global batch, so it is the same on any number of
    processes and after a resume."""
    import numpy as np

    return int(np.random.SeedSequence([int(seed), int(stage), int(step), int(position)]).generate_state(1)[0])


# -- the trainer ---------------------------------------------------------------------------------
class Trainer:
    """Trains one stage on a map-style dataset of pair dicts (see docs/manifest.md, "The dataset adapter").

    ``init``: weights to start from (a trainer checkpoint or a bare state dict). Stage 2 needs the
    stage-1 weights; its new modules start fresh. A ``last.pt`` in ``out_dir`` takes precedence:
    the run resumes from it (or from ``previous.pt``, the one before, when ``last.pt`` is damaged).

    Data parallel: started by torchrun, each process trains on its own pairs of every global batch
    (the adapter's rank split, :func:`paradrive.data.epoch_order`), gradients are averaged over the
    processes (DDP) and rank 0 alone writes the run folder. ``train.batch_size`` is per process and
    per micro-batch; a step averages ``train.grad_accumulation`` micro-batches on every process.
    """

    # what a checkpoint says it is, and the settings a resumed run must share with it
    checkpoint_format = CHECKPOINT_FORMAT
    checkpoint_keys: tuple[str, ...] = CHECKPOINT_KEYS
    resume_keys: tuple[str, ...] = ("model", "autoencoder", "seed")

    def _restore(self, stage: int, init: str | Path | None) -> bool:
        """The counters at their start, then the run's ``last.pt`` (resume; ``previous.pt`` when
        it is damaged), else ``init``; stage 2 needs one of them. True when neither was there: a
        stage 1 starting afresh."""
        self.step = self.epoch = self.batch_in_epoch = 0
        self._pending_optimizer: dict | None = None
        self._pending_ema: dict | None = None
        resume = self._resume_checkpoint()
        if resume is not None:
            self._load(*resume)
        elif init is not None:
            self._init_from(Path(init))
        elif stage == 2:
            raise ValueError("stage 2 starts from stage-1 weights: pass --init <stage-1 checkpoint> "
                             "(e.g. <out>/stage1/last.pt)")
        else:
            return True
        return False

    def _resume_checkpoint(self) -> tuple[Path, dict] | None:
        """(path, contents) of the newest whole checkpoint of this run, ``last.pt`` else
        ``previous.pt``; None for a new run. A damaged ``last.pt`` with a whole ``previous.pt`` is
        noted (:attr:`notes`); with none whole, one line saying what is wrong and what to do."""
        last, previous = self.out_dir / "last.pt", self.out_dir / PREVIOUS
        problems = []
        for path in (last, previous):
            if not path.is_file():
                continue
            try:
                ckpt = read_checkpoint(path, f"stage {self.stage}'s", self.checkpoint_keys, self.device)
            except DamagedCheckpoint as exc:
                problems.append(str(exc))
                continue
            if problems:
                self.notes.append(f"{problems[0]}; resuming from {path} (step {ckpt['step']}), the "
                                  f"checkpoint before it")
                self._rotate = False   # the damaged last.pt is overwritten, never kept as previous.pt
            elif path == previous:
                self.notes.append(f"{last} is missing (a run stopped while replacing it); resuming from "
                                  f"{path} (step {ckpt['step']})")
            return path, ckpt
        if problems:
            raise DamagedCheckpoint(f"{problems[0]}, and no earlier whole checkpoint is there to resume from; "
                                    f"delete {self.out_dir} to train stage {self.stage} from the start, or use "
                                    f"another --out")
        return None

    def _start(self, config: Mapping[str, Any], stage: int, out_dir: str | Path, dataset) -> int:
        """What every trainer holds before its model: the config, stage, run folder, data, device
        and place among the run's processes; torch's generator seeded. Returns the seed."""
        if stage not in (1, 2):
            raise ValueError(f"stage must be 1 or 2, got {stage}")
        self.config = copy.deepcopy(dict(config))
        self.stage = stage
        self.out_dir = Path(out_dir)
        self.dataset = dataset
        device = resolve_device(self.config["device"])
        self.world = join(device)
        self.device = device_for(device, self.world)
        if self.device.type == "cuda":
            torch.cuda.set_device(self.device)
        self.notes: list[str] = []   # what a user should read: a fallback to an earlier checkpoint
        self._rotate = True           # the next save keeps the last.pt it replaces as previous.pt
        self._ddp: torch.nn.Module | None = None
        self._sharded = False   # train.fsdp: the model's tensors are shards (DTensors) from the first step
        t = self.config["train"]
        self.batch_size, self.accumulation = int(t["batch_size"]), int(t["grad_accumulation"])
        need = self.batch_size * self.accumulation
        if per_rank(len(dataset), self.world.world_size) < need:
            raise ValueError(f"the dataset has {len(dataset)} pairs: {self.world.world_size} process(es) at "
                             f"train.batch_size={self.batch_size} x train.grad_accumulation={self.accumulation} "
                             f"need {need * self.world.world_size} for one step; lower them or add pairs")
        seed = int(self.config["seed"])
        torch.manual_seed(seed)
        return seed

    def __init__(self, config: Mapping[str, Any], stage: int, out_dir: str | Path, dataset,
                 init: str | Path | None = None):
        self._start(config, stage, out_dir, dataset)
        self.encoder = make_autoencoder(self.config["autoencoder"])
        if isinstance(self.encoder, torch.nn.Module):
            self.encoder.to(self.device).eval()
        self.model = build_model(self.config, stage, self.encoder).to(self.device)
        t = self.config["train"]
        self._restore(stage, init)
        mask = trainable_mask(self.model, stage, t["stage1_trainable"])
        for name, p in self.model.named_parameters():
            p.requires_grad_(mask[name])
        self._make_optimizer([p for p in self.model.parameters() if p.requires_grad])

    def _make_optimizer(self, params: list[torch.nn.Parameter]) -> None:
        """AdamW over the trained ``params`` (with a resumed run's state)."""
        t = self.config["train"]
        self.optimizer = torch.optim.AdamW(params, lr=float(t["lr"]), betas=tuple(t["betas"]),
                                           weight_decay=float(t["weight_decay"]), eps=float(t["eps"]))
        if self._pending_optimizer is not None:
            try:
                self.optimizer.load_state_dict(self._pending_optimizer)
            except (ValueError, KeyError) as exc:
                raise DamagedCheckpoint(f"{self.out_dir / 'last.pt'}: its optimiser state does not fit this "
                                        f"run's trained parameters ({exc}); use another --out") from exc
        self._pending_optimizer = None
        self._make_ema()

    def _make_ema(self) -> None:
        """The exponential moving average of the trained parameters (``train.ema_decay``; null =
        off): a resumed run's from its checkpoint, else a copy of the weights the run starts from."""
        decay = self.config["train"].get("ema_decay")
        pending, self._pending_ema = self._pending_ema, None
        self.ema: dict[str, torch.Tensor] | None = None
        if decay is None:
            return
        trained = {n: p.detach() for n, p in self.model.named_parameters() if p.requires_grad}
        if pending is None:
            if self.step > 0:
                self.notes.append(f"train.ema_decay={decay}: the checkpoint resumed at step {self.step} holds no "
                                  f"EMA; it starts from the resumed weights")
            self.ema = {n: p.clone() for n, p in trained.items()}
            return
        if set(pending) != set(trained):
            raise DamagedCheckpoint(f"{self.out_dir / 'last.pt'}: its EMA does not fit this run's trained "
                                    f"parameters; use another --out")
        self.ema = {n: pending[n].to(device=p.device, dtype=p.dtype).clone() for n, p in trained.items()}

    @torch.no_grad()
    def _update_ema(self) -> None:
        """ema <- decay * ema + (1 - decay) * weights, after each optimiser step."""
        if self.ema is None:
            return
        decay = float(self.config["train"]["ema_decay"])
        params = dict(self.model.named_parameters())
        for name, average in self.ema.items():
            average.mul_(decay).add_(params[name].detach(), alpha=1.0 - decay)

    @contextlib.contextmanager
    def averaged(self) -> Iterator[None]:
        """The model with the EMA in place of its trained weights for the duration (unchanged
        without an EMA); the trained weights are back afterwards."""
        if self.ema is None:
            yield
            return
        params = dict(self.model.named_parameters())
        kept = {n: params[n].detach().clone() for n in self.ema}
        with torch.no_grad():
            for name, average in self.ema.items():
                params[name].copy_(average)
        try:
            yield
        finally:
            with torch.no_grad():
                for name, value in kept.items():
                    params[name].copy_(value)

    # -- weights -----------------------------------------------------------------------------------
    def _init_from(self, path: Path) -> None:
        if not path.is_file():
            raise FileNotFoundError(f"--init {path}: no such checkpoint")
        ckpt = read_checkpoint(path, "--init", keys=(), map_location=self.device)
        state = ckpt.get("model", ckpt)
        if "config" in ckpt:
            for key in ("model", "autoencoder"):
                if ckpt["config"].get(key) != self.config[key]:
                    raise ValueError(f"--init {path}: its {key} settings {ckpt['config'].get(key)} differ from "
                                     f"this run's {self.config[key]}; use the same training config")
        try:
            load_stage1_weights(self.model, state)
        except RuntimeError as exc:  # tensor size mismatch
            raise ValueError(f"--init {path}: weights do not fit this model ({exc}); use the same training "
                             f"config") from exc
        log.info("initialised from %s", path)

    def _load(self, path: Path, ckpt: dict) -> None:
        if ckpt.get("format") != self.checkpoint_format or ckpt.get("stage") != self.stage:
            raise ValueError(f"{path}: not a stage-{self.stage} checkpoint of this trainer ({self.checkpoint_format}); "
                             f"use another --out or delete it to start over")
        for key in self.resume_keys:
            if ckpt["config"].get(key) != self.config[key]:
                raise ValueError(f"{path}: was trained with {key}={ckpt['config'].get(key)}, this run has "
                                 f"{self.config[key]}; resume with the same config or use another --out")
        for key in ("batch_size", "grad_accumulation"):
            if ckpt["config"]["train"].get(key) != self.config["train"][key]:
                raise ValueError(f"{path}: was trained with train.{key}={ckpt['config']['train'].get(key)}, this "
                                 f"run has {self.config['train'][key]} (the data position depends on it); resume "
                                 f"with the same value or use another --out")
        if ckpt["world_size"] != self.world.world_size:
            raise ValueError(f"{path}: was trained on {ckpt['world_size']} process(es), this run has "
                             f"{self.world.world_size}; resume with torchrun --nproc_per_node "
                             f"{ckpt['world_size']} (the data order and batches depend on it) or use another --out")
        self._load_model_state(path, ckpt)
        self._pending_optimizer = ckpt["optimizer"]
        self._pending_ema = ckpt.get("ema")
        self.step, self.epoch, self.batch_in_epoch = ckpt["step"], ckpt["epoch"], ckpt["batch_in_epoch"]
        torch.set_rng_state(ckpt["torch_rng"])
        log.info("resumed %s at step %d", path, self.step)

    def _load_model_state(self, path: Path, ckpt: dict) -> None:
        """The model's weights from a resumed checkpoint (all of them, for this trainer)."""
        try:
            self.model.load_state_dict(ckpt["model"])
        except RuntimeError as exc:
            raise DamagedCheckpoint(f"{path}: its weights do not fit this model ({str(exc).splitlines()[0]}); "
                                    f"use another --out") from exc

    def model_state(self) -> dict[str, torch.Tensor]:
        """The weights a checkpoint holds (all of them, for this trainer)."""
        return self.model.state_dict()

    def state_dict(self) -> dict:
        """The checkpoint's contents: whole tensors, gathered from every process when the model is
        sharded (then every process must call it)."""
        from paradrive.train.sharding import whole

        state = {"format": self.checkpoint_format, "stage": self.stage, "step": self.step, "epoch": self.epoch,
                 "batch_in_epoch": self.batch_in_epoch, "world_size": self.world.world_size,
                 "config": self.config, "model": whole(self.model_state()),
                 "optimizer": whole(self.optimizer.state_dict()), "torch_rng": torch.get_rng_state()}
        if self.ema is not None:
            state["ema"] = whole(self.ema)
        return state

    def save(self) -> Path:
        """Write ``last.pt`` (and ``ckpt_<step>.pt`` on checkpoint steps) atomically; the checkpoint
        it replaces stays as ``previous.pt``, the fallback of a damaged ``last.pt``. Rank 0 writes;
        with a sharded model every process calls it (its tensors are gathered first)."""
        state = self.state_dict()
        last = self.out_dir / "last.pt"
        if not self.world.main:
            return last
        self.out_dir.mkdir(parents=True, exist_ok=True)
        with atomic_path(last) as tmp:
            torch.save(state, tmp)
            if last.exists() and self._rotate:
                os.replace(last, self.out_dir / PREVIOUS)
        self._rotate = True
        every = int(self.config["train"]["checkpoint_every"])
        if every and self.step % every == 0:
            with atomic_path(self.out_dir / f"ckpt_{self.step:06d}.pt") as tmp:
                torch.save(state, tmp)
            self._prune()
        return last

    def _prune(self) -> None:
        """Delete the ``ckpt_<step>.pt`` files beyond the ``train.keep_last`` newest (0 = keep
        all), except those of every ``train.keep_every``-th step (0 = none such)."""
        t = self.config["train"]
        keep_last, keep_every = int(t["keep_last"]), int(t["keep_every"])
        if keep_last <= 0:
            return
        steps = {}
        for path in self.out_dir.glob("ckpt_*.pt"):
            digits = path.stem[len("ckpt_"):]
            if digits.isdigit():
                steps[path] = int(digits)
        by_step = sorted(steps, key=steps.__getitem__)
        for old in by_step[:-keep_last]:
            if not (keep_every and steps[old] % keep_every == 0):
                old.unlink()

    # -- data --------------------------------------------------------------------------------------
    def _epoch_steps(self, epoch: int) -> list[list[list[int]]]:
        """This process's micro-batches of each step of ``epoch``: its share of the epoch's order
        (:func:`paradrive.data.epoch_order`, rank r reads every world_size-th pair from r), cut into
        steps of grad_accumulation micro-batches of batch_size; an incomplete last step dropped."""
        w = self.world
        order = epoch_order(len(self.dataset), int(self.config["seed"]), epoch, w.world_size)[w.rank::w.world_size]
        b, per_step = self.batch_size, self.batch_size * self.accumulation
        return [[order[s * per_step + m * b:s * per_step + (m + 1) * b].tolist() for m in range(self.accumulation)]
                for s in range(len(order) // per_step)]

    def _batches(self) -> Iterator[list[dict]]:
        """The micro-batches of each step from the current (epoch, batch_in_epoch) on; the caller
        advances the position."""
        workers = int(self.config["data"]["num_workers"])
        while True:
            steps = self._epoch_steps(self.epoch)[self.batch_in_epoch:]
            loader = torch.utils.data.DataLoader(self.dataset, batch_sampler=[m for s in steps for m in s],
                                                 num_workers=workers, collate_fn=collate, persistent_workers=False)
            micro: list[dict] = []
            for batch in loader:
                micro.append(batch)
                if len(micro) == self.accumulation:
                    yield micro
                    micro = []
            self.epoch += 1
            self.batch_in_epoch = 0

    def _generators(self, micro: int) -> list[torch.Generator]:
        """One generator per sample of micro-batch ``micro`` of this step, seeded by the sample's
        place in the global batch: ((micro * batch_size + i) * world_size + rank)."""
        w, b = self.world, self.batch_size
        seed = int(self.config["seed"])
        return [torch.Generator().manual_seed(sample_seed(seed, self.stage, self.step,
                                                          (micro * b + i) * w.world_size + w.rank))
                for i in range(b)]

    # -- one step ----------------------------------------------------------------------------------
    def forward(self, *inputs: Any) -> torch.Tensor:
        """The model's forward for training: through DDP in a run of several processes."""
        return (self._ddp or self.model)(*inputs)

    def latents(self, batch: Mapping[str, Any]) -> dict[str, torch.Tensor]:
        """Encode a batch: target/source(/condition) latents and per-latent-frame poses."""
        frames = batch["target"].shape[1]
        groups = self.encoder.frame_groups(frames)
        with torch.no_grad():
            out = {k: self.encoder.encode(frames_on(batch[k], self.device)) for k in ("target", "source")}
            if self.stage == 2:
                out["condition"] = self.encoder.encode(frames_on(batch["condition"], self.device))
        out["rel_pose"] = latent_poses(batch["rel_pose"].to(self.device), groups)
        out["identity_pose"] = latent_poses(batch["identity_pose"].to(self.device), groups)
        return out

    def loss(self, z: Mapping[str, torch.Tensor], generator: Generators) -> torch.Tensor:
        """Flow-matching loss on the target half for encoded batch ``z``; noise and times from
        ``generator`` (one, or one per sample)."""
        f = self.config["flow"]

        def velocity(x_t, t):
            return self.forward(x_t, t, z["source"], z["rel_pose"], z["identity_pose"], z.get("condition"))

        return flow_matching_loss(velocity, z["target"], generator, f["schedule"], float(f["shift"]),
                                  f["weighting"])

    @torch.no_grad()
    def evaluate(self, batch: Mapping[str, Any], seed: int = 0, repeats: int = 8) -> float:
        """Loss on ``batch`` with noise and times fixed by ``seed`` (averaged over ``repeats``
        draws): comparable between calls, unlike the training loss of single random draws."""
        was_training = self.model.training
        self.model.eval()
        with torch_threads(self.config["threads"]):
            z = self.latents(batch)
            g = torch.Generator().manual_seed(seed)
            value = sum(float(self.loss(z, g)) for _ in range(repeats)) / repeats
        self.model.train(was_training)
        return value

    def learning_rate(self, step: int) -> float:
        """The rate of optimiser step ``step`` (0-based): :func:`scheduled_lr` of the config."""
        return scheduled_lr(self.config["train"], step)

    def train(self, steps: int | None = None,
              on_step: Callable[[int, float], None] | None = None) -> list[float]:
        """Train until ``steps`` total steps (default ``train.steps``); return this call's losses
        (each the mean over the step's micro-batches and processes)."""
        with torch_threads(self.config["threads"]):
            return self._train(steps, on_step)

    def _wrap(self) -> None:
        """DDP around the model in a run of several processes (once); with ``train.fsdp`` the
        model sharded over them instead (:mod:`paradrive.train.sharding`)."""
        if not self.world.distributed or self._ddp is not None or self._sharded:
            return
        if self.config["train"].get("fsdp"):
            from paradrive.train.sharding import shard_training

            self.optimizer, self.ema = shard_training(self.model, self.optimizer, self.ema)
            self._sharded = True
            return
        from torch.nn.parallel import DistributedDataParallel

        ids = [self.device.index] if self.device.type == "cuda" else None
        self._ddp = DistributedDataParallel(self.model, device_ids=ids)

    def _write_run_files(self) -> None:
        """config.yaml (with the stage and the world size) and metrics.jsonl cut at the resumed
        step; rank 0 writes, the others wait for it."""
        if self.world.main:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            write_text(self.out_dir / "config.yaml", yaml.safe_dump(
                {"stage": self.stage, "world_size": self.world.world_size, **self.config}, sort_keys=False))
            self._trim_metrics()
        barrier(self.world)

    def _step(self, micro: list[dict]) -> float:
        """One optimiser step over this process's micro-batches; the loss averaged over them and
        over the processes."""
        self.optimizer.zero_grad(set_to_none=True)
        value = 0.0
        for m, batch in enumerate(micro):
            last = m == len(micro) - 1
            sync = contextlib.nullcontext() if self._ddp is None or last else self._ddp.no_sync()  # type: ignore[operator]
            with sync:
                loss = self.loss(self.latents(batch), self._generators(m))
                if not all_agree(bool(torch.isfinite(loss)), self.world):
                    raise FloatingPointError(f"the loss is not finite on some process ({loss.item()} here); "
                                             f"lower train.lr or check the data ({batch['pair_id']})")
                (loss / len(micro)).backward()
            value += float(loss.detach()) / len(micro)
        clip = float(self.config["train"]["grad_clip"])
        if clip > 0:
            torch.nn.utils.clip_grad_norm_([p for p in self.model.parameters() if p.requires_grad], clip)
        self.optimizer.step()
        self._update_ema()
        return mean_over_ranks(value, self.world, self.device)

    def _train(self, steps: int | None, on_step: Callable[[int, float], None] | None) -> list[float]:
        total = int(self.config["train"]["steps"] if steps is None else steps)
        t = self.config["train"]
        self._write_run_files()
        losses: list[float] = []
        if self.step >= total:
            return losses
        self._wrap()
        self.model.train()
        save_every, every_ckpt = int(t["save_every"]), int(t["checkpoint_every"])
        global_batch = self.batch_size * self.accumulation * self.world.world_size
        started = time.time()
        metrics = open(self.out_dir / "metrics.jsonl", "a") if self.world.main else None
        with metrics if metrics is not None else contextlib.nullcontext():
            for micro in self._batches():
                lr = self.learning_rate(self.step)
                for group in self.optimizer.param_groups:
                    group["lr"] = lr
                value = self._step(micro)
                self.step += 1
                self.batch_in_epoch += 1
                losses.append(value)
                if metrics is not None:
                    metrics.write(json.dumps({"step": self.step, "loss": value, "lr": lr,
                                              "world_size": self.world.world_size, "global_batch": global_batch,
                                              "seconds": round(time.time() - started, 3)}) + "\n")
                    metrics.flush()
                if on_step and self.world.main:
                    on_step(self.step, value)
                if self.step >= total or (save_every and self.step % save_every == 0) \
                        or (every_ckpt and self.step % every_ckpt == 0):
                    if self.world.main or self._sharded:
                        self.save()
                    if self.world.main:
                        stop_point(f"train:stage{self.stage}-saved-{self.step}")
                    barrier(self.world)
                if self.step >= total:
                    break
        return losses

    def _trim_metrics(self) -> None:
        """Drop metric lines past the resumed step (a killed run may have logged beyond its last save)."""
        path = self.out_dir / "metrics.jsonl"
        if not path.exists():
            return
        text = path.read_text()
        kept = [line for line in text.splitlines() if (_metric_step(line) or self.step + 1) <= self.step]
        if "".join(l + "\n" for l in kept) != text:
            write_text(path, "".join(l + "\n" for l in kept))


def _metric_step(line: str) -> int | None:
    """The step of a metrics line; None for a blank one or one cut off by a kill."""
    try:
        return int(json.loads(line)["step"])
    except (ValueError, KeyError, TypeError):
        return None


# -- sampling ------------------------------------------------------------------------------------
def load_for_sampling(checkpoint: str | Path, device: str = "auto",
                      autoencoder: Mapping[str, Any] | None = None) -> tuple[VideoDiT, VideoEncoder, dict, int]:
    """(model, autoencoder, config, stage) from a trainer checkpoint, in eval mode.

    A checkpoint whose autoencoder is imported by name (``kind: "pkg.module:Factory"``) names
    code to run; it is refused unless ``autoencoder`` (the caller's own config section) says the same.
    """
    ckpt = load_tensors(checkpoint)
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{checkpoint}: not a paradrive trainer checkpoint")
    named = ckpt["config"]["autoencoder"]
    if named.get("kind", "patch") != "patch" and named != autoencoder:
        raise UnsafeFileError(f"{checkpoint}: its autoencoder is code imported by name "
                              f"({named.get('kind')!r}); refused unless the caller passes the same "
                              f"autoencoder config (autoencoder=...)")
    dev = resolve_device(device)
    encoder = make_autoencoder(ckpt["config"]["autoencoder"])
    if isinstance(encoder, torch.nn.Module):
        encoder.to(dev).eval()
    model = build_model(ckpt["config"], ckpt["stage"], encoder)
    model.load_state_dict(averaged_weights(ckpt))
    return model.to(dev).eval(), encoder, ckpt["config"], ckpt["stage"]


def averaged_weights(ckpt: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """A checkpoint's weights for sampling: its ``model`` with the EMA of the trained parameters in
    their place when it holds one (``train.ema_decay``), else its ``model`` as it is."""
    return {**ckpt["model"], **(ckpt.get("ema") or {})}


@torch.no_grad()
def sample_video(model: VideoDiT, encoder: VideoEncoder, sample: Mapping[str, Any], steps: int,
                 seed: int = 0, shift: float = 1.0) -> torch.Tensor:
    """Generate the target-trajectory video of one pair dict (unbatched tensors, as the adapter
    gives them) from its source, ΔT and (stage 2) condition. Returns (F, 3, H, W) in [-1, 1]."""
    device = next(model.parameters()).device
    batch = collate([dict(sample)])
    groups = encoder.frame_groups(batch["source"].shape[1])
    x_s = encoder.encode(frames_on(batch["source"], device))
    rel = latent_poses(batch["rel_pose"].to(device), groups)
    ident = latent_poses(batch["identity_pose"].to(device), groups)
    cond = encoder.encode(frames_on(batch["condition"], device)) if model.config.rendering else None
    noise = torch.randn(x_s.shape, generator=torch.Generator().manual_seed(seed)).to(device)
    z = euler_sample(lambda x, t: model(x, t, x_s, rel, ident, cond), noise, steps, shift)
    return encoder.decode(z)[0].clamp(-1, 1).cpu()


def write_video(path: str | Path, video: torch.Tensor, fps: float) -> Path:
    """Write (F, 3, H, W) in [-1, 1] as an H.264 mp4 (even H and W), atomically."""
    import av
    from fractions import Fraction

    frames = ((video.clamp(-1, 1) + 1) * 127.5).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()
    _, h, w, _ = frames.shape
    path = Path(path)
    with atomic_path(path) as tmp:
        with av.open(str(tmp), mode="w", format="mp4") as container:
            stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
            stream.width, stream.height, stream.pix_fmt = w, h, "yuv420p"
            for frame in frames:
                for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                    container.mux(packet)
            for packet in stream.encode():
                container.mux(packet)
    return path
