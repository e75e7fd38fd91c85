"""``paradrive generate``: a trained ReCamDriving model run on an inference build.

For every row of the build (``paradrive build --kind inference``: the recording as source, the
shifted 3DGS render as condition, ΔT) the model samples the novel-trajectory video from noise in
``sample.steps`` Euler steps (the flow's ``shift`` as trained), the VAE decodes it, and it is
written as ``OUT/<pair_id>.mp4``: the names ``paradrive eval --build BUILD --videos OUT`` scores.

The checkpoint is a run folder's ``last.pt`` (``<out>/stage2``, or a ``.pt`` file): its trained
parameters go onto the base transformer it names (its folder, or ``--transformer``), checked by
the fingerprint of the base's config, with the EMA of the trained parameters in their place when
the run kept one (``train.ema_decay``). A row that cannot be read is reported in one line and the
others go on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from paradrive.devices import resolve_device
from paradrive.errors import ConfigError, ParaDriveError
from paradrive.io import path_inside
from paradrive.train.trainer import averaged_weights, read_checkpoint, torch_threads, write_video
from paradrive.wan.recam import checkpoint_parameter_names, load_trained
from paradrive.train.wan import (WanRunner, base_record, build_wan_model, check_base, check_format,
                                 generated_frames, open_wan_dataset)

__all__ = ["Generator", "GenerateReport", "checkpoint_file", "load_generator", "generate"]


class Generator(WanRunner):
    """A trained stage's model (eval mode) with its VAE and text embedding, ready to sample."""

    def __init__(self, config: dict, stage: int, device: torch.device, model: torch.nn.Module):
        self.config, self.stage, self.device, self.model = config, stage, device, model
        self._setup_inputs()
        self.model.eval()


def checkpoint_file(checkpoint: Path) -> Path:
    """A run folder's ``last.pt`` (``<out>/stage2``), or the file itself."""
    path = checkpoint / "last.pt" if checkpoint.is_dir() else checkpoint
    if not path.is_file():
        raise FileNotFoundError(f"--checkpoint {checkpoint}: no checkpoint there (a stage folder of "
                                f"'paradrive train --model wan', e.g. runs/<build>/stage2, or its last.pt)")
    return path


def load_generator(checkpoint: Path, folders: dict[str, str | None], device: str | None = None) -> Generator:
    """The model of a ``paradrive train --model wan`` checkpoint: its base transformer
    (``folders["transformer"]`` or the one it was trained on) with its trained parameters;
    ``folders`` (``vae``, ``text_encoder``) replace the run's own when given."""
    path = checkpoint_file(checkpoint)
    ckpt = read_checkpoint(path, "--checkpoint", ("format", "stage", "config", "model", "base"))
    check_format(ckpt["format"], f"--checkpoint {path}")
    config = ckpt["config"]
    config["model"].update({k: str(v) for k, v in folders.items() if v is not None})
    if folders.get("transformer") is None:
        config["model"]["transformer"] = ckpt["base"]["folder"]
    if device is not None:
        config["device"] = device
    stage = int(ckpt["stage"])
    where = resolve_device(config["device"])
    model = build_wan_model(config, stage)
    check_base(ckpt, base_record(config, model), f"--checkpoint {path}")
    names = checkpoint_parameter_names(model, stage, bool(config["model"]["stage2_ffn"]))
    # the EMA of the trained parameters, when the run kept one (train.ema_decay), is what samples
    load_trained(model, averaged_weights(ckpt), names, f"--checkpoint {path}")
    return Generator(config, stage, where, model.to(where))


@dataclass
class GenerateReport:
    written: list[Path] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)   # one line per row that could not be generated
    notes: list[str] = field(default_factory=list)    # how the rows were read (a latent cache not used)


def generate(build: Path, generator: Generator, out: Path, steps: int | None = None, limit: int | None = None,
             on_row: Callable[[int, int, str], None] | None = None) -> GenerateReport:
    """One video per row of ``build`` (the first ``limit``) into ``out``/<pair_id>.mp4. Usage
    errors (ConfigError) come before any video is made."""
    config = generator.config
    if not build.is_dir():
        raise FileNotFoundError(f"--build {build}: no such build folder (paradrive build --kind inference writes one)")
    report = GenerateReport()
    dataset = open_wan_dataset(build, config, report.notes)
    frames = generated_frames(int(config["data"]["num_frames"]))
    rows = list(range(len(dataset)))[:limit]
    clip = {int(dataset.row(i)["num_frames"]) for i in rows}
    if clip != {frames}:
        raise ConfigError(f"--build {build}: its clips have {sorted(clip)} frames, the model generates {frames} "
                          f"(data.num_frames={config['data']['num_frames']}); paradrive eval scores whole clips: "
                          f"build the inference set with render.clip_frames={frames}, or train on clips of theirs")
    s = config["sample"]
    for k, i in enumerate(rows):
        pair_id = dataset.pair_ids[i]
        try:
            path = path_inside(out, f"{pair_id}.mp4", f"{build}: pair {pair_id}")
            with torch_threads(config["threads"]):
                video = generator.sample(dataset[i], steps or int(s["steps"]), seed=int(s["seed"]))
            path.parent.mkdir(parents=True, exist_ok=True)
            report.written.append(write_video(path, video, float(s["fps"])))
        except ParaDriveError as exc:
            report.failed.append(f"{pair_id}: {exc}")
        if on_row is not None:
            on_row(k + 1, len(rows), pair_id)
    return report
