"""A training run as ``paradrive train`` starts it (:mod:`paradrive.commands.train`): the config
of ``--model`` (``reference``, the small stand-in, or ``wan``, ReCamDriving on Wan2.1), the build's
pairs as that model's trainer reads them, the trainer of a stage in its run folder, and the
samples written after training. Nothing here prints; the command reports what these return."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from paradrive.errors import ConfigError
from paradrive.io import path_inside


@dataclass
class Run:
    """A started run: its config, the build's pairs, the stage's trainer and its folder, and
    what a user should know of how it was set up (``notes``)."""

    cfg: dict
    dataset: Any
    trainer: Any
    stage_dir: Path
    notes: list[str] = field(default_factory=list)


def start_run(build: Path, stage: int, config: str | None, out_dir: Path | None, init: Path | None,
              overrides: dict, model: str, folders: dict[str, Path | None]) -> Run:
    """The trainer of ``stage`` on ``build``'s pairs, in ``<out_dir>/stage<k>`` (default
    ``runs/<build name>``); stage 2 starts from stage 1's ``last.pt`` unless ``init`` says
    otherwise. Raises ValueError, FileNotFoundError or ParaDriveError naming what is wrong."""
    cfg = load_run_config(model, config, overrides, folders)
    if model == "wan":
        check_weight_folders(cfg["model"])
    if not build.is_dir():
        raise FileNotFoundError(f"--build {build}: no such build folder (run 'paradrive build' first)")
    run_dir = out_dir if out_dir is not None else Path("runs") / build.resolve().name
    stage_dir = run_dir / f"stage{stage}"
    if stage == 2 and init is None and not (stage_dir / "last.pt").exists():
        init = run_dir / "stage1" / "last.pt"
        if not init.exists():
            raise FileNotFoundError(f"stage 2 needs stage-1 weights: none at {init}; run "
                                    f"'paradrive train --stage 1' with the same --out, or pass --init")
    notes: list[str] = []
    dataset = open_pairs(model, build, cfg, notes)
    trainer = trainer_class(model)(cfg, stage, stage_dir, dataset, init=init)
    return Run(cfg, dataset, trainer, stage_dir, notes)


def load_run_config(model: str, config: str | None, overrides: dict, folders: dict[str, Path | None]) -> dict:
    """The training config of ``--model``: ``wan`` reads ``stages/train/wan-<name>.yaml`` and takes
    the weights folders given on the command line; ``reference`` refuses a wan config."""
    from paradrive.train.trainer import load_config

    if model == "wan":
        from paradrive.train.wan import load_wan_config

        overrides.setdefault("model", {}).update({k: str(v) for k, v in folders.items() if v is not None})
        return load_wan_config(config, overrides)
    if model != "reference":
        raise ValueError(f"--model {model}: use reference or wan")
    cfg = load_config(config, overrides)
    if "autoencoder" not in cfg:   # a wan-* config names Wan's folders, not a patch codec
        raise ValueError(f"--config {config} is a config of --model wan; add --model wan")
    return cfg


_FLAGS = {"transformer": "--transformer", "vae": "--vae", "text_encoder": "--text-encoder"}


def check_weight_folders(settings: dict) -> None:
    """ConfigError before any work when ``model.transformer``, ``model.vae`` or
    ``model.text_encoder`` names a folder that does not exist or lacks what is loaded from it
    (``tiny`` and unset ones are left alone): one line naming the flag, the path and the layout."""
    from paradrive.wan.text import text_encoder_folders
    from paradrive.wan.vae import vae_folder

    for key, flag in _FLAGS.items():
        value = settings.get(key)
        if value in (None, "tiny"):
            continue
        folder = Path(str(value))
        if not folder.is_dir():
            raise ConfigError(f"{flag} {folder}: no such folder; pass the local Wan2.1-T2V-1.3B diffusers "
                              f"folder (it holds transformer/, vae/, text_encoder/ and tokenizer/)")
        if key == "transformer":
            inner = folder / "transformer" if (folder / "transformer" / "config.json").is_file() else folder
            if not (inner / "config.json").is_file() or not any(inner.glob("*.safetensors")):
                raise ConfigError(f"{flag} {folder}: no config.json and safetensors weights there nor in "
                                  f"{folder / 'transformer'}; pass the Wan2.1-T2V-1.3B diffusers folder (it "
                                  f"holds transformer/) or its transformer/ folder")
        else:
            try:
                vae_folder(folder) if key == "vae" else text_encoder_folders(folder)
            except ConfigError as exc:
                raise ConfigError(f"{flag}: {exc}") from exc


def open_pairs(model: str, build: Path, cfg: dict, notes: list[str] | None = None):
    """The build's pairs as ``--model``'s trainer reads them (``notes``: what a user should know
    of how, e.g. a latent cache that does not fit)."""
    if model == "wan":
        from paradrive.train.wan import open_wan_dataset

        return open_wan_dataset(build, cfg, notes)
    from paradrive.train.trainer import open_dataset

    return open_dataset(build, cfg)


def trainer_class(model: str) -> type:
    from paradrive.train.trainer import Trainer

    if model == "wan":
        from paradrive.train.wan import WanTrainer

        return WanTrainer
    return Trainer


def find_pair(dataset, pair: str) -> dict:
    """The pair ``--pair`` names: its index in the build (negative from the end) or its pair_id."""
    if pair.lstrip("-").isdigit():
        index = int(pair)
        if not -len(dataset) <= index < len(dataset):
            raise IndexError(f"--pair {index}: the build has {len(dataset)} pairs")
        return dataset[index]
    ids = getattr(dataset, "pair_ids", None)
    ids = list(ids) if ids is not None else [dataset[i]["pair_id"] for i in range(len(dataset))]
    if pair not in ids:
        raise ValueError(f"--pair {pair!r}: no such pair_id in the build (e.g. {ids[0]!r})")
    return dataset[ids.index(pair)]


def sample_picks(run: Run, model: str, sample: Path, pair: str,
                 sample_set: Path | None) -> list[tuple[Callable[[], dict], Path]]:
    """What to sample and where: every row of ``sample_set`` into ``sample/<pair_id>.mp4``, or
    the one pair ``pair`` of the run's build into the file ``sample``; each row is read when
    its turn comes."""
    if sample_set is not None:
        items = open_pairs(model, sample_set, run.cfg)
        # a pair id names the file; one from a shared build must stay inside the folder
        return [(functools.partial(items.__getitem__, i),
                 path_inside(sample, f"{pid}.mp4", f"{sample_set}: pair {pid}"))
                for i, pid in enumerate(items.pair_ids)]
    item = find_pair(run.dataset, pair)
    return [(functools.partial(dict, item), sample)]


def write_sample(run: Run, item: dict, path: Path, steps: int | None) -> int:
    """Generate ``item``'s target video with the trained model (``steps`` Euler steps, default
    ``sample.steps``) and write it to ``path``; returns its frames."""
    from paradrive.train.trainer import sample_video, torch_threads, write_video
    from paradrive.train.wan import WanTrainer

    cfg, trainer, s = run.cfg, run.trainer, run.cfg["sample"]
    trainer.model.eval()
    with torch_threads(cfg["threads"]), trainer.averaged():   # the EMA weights when the run keeps them
        if isinstance(trainer, WanTrainer):   # decodes through the VAE
            video = trainer.sample(item, steps or int(s["steps"]), seed=int(s["seed"]))
        else:
            video = sample_video(trainer.model, trainer.encoder, item, steps or int(s["steps"]),
                                 seed=int(s["seed"]), shift=float(cfg["flow"]["shift"]))
    path.parent.mkdir(parents=True, exist_ok=True)
    write_video(path, video, float(s["fps"]))
    return int(video.shape[0])
