"""``paradrive train``: train stage 1 or 2 of the reference model on a build, and write samples."""

from __future__ import annotations

import functools

from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape

from paradrive.errors import EXIT_FAILED, ParaDriveError
from paradrive.io import path_inside

console = Console(stderr=True)


def _fail(message: str) -> None:
    console.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True)   # one line, whatever the width
    raise typer.Exit(2)


def train(
    build: Path = typer.Option(..., "--build", help="A build folder (<manifests>/<build>) to read pairs from."),
    stage: int = typer.Option(1, "--stage", min=1, max=2, help="1: relative-pose control; 2: add 3DGS renderings (stage-1 weights frozen)."),
    config: str | None = typer.Option(None, "--config", help="Training config: a name in stages/train/ (default, smoke) or a YAML file."),
    out_dir: Path | None = typer.Option(None, "--out", help="Run folder; stage k writes <out>/stage<k>. Default: runs/<build name>."),
    steps: int | None = typer.Option(None, "--steps", min=0, help="Train until this many steps in total (default: train.steps). A finished run resumes and stops at once."),
    init: Path | None = typer.Option(None, "--init", help="Weights to start from; stage 2 defaults to <out>/stage1/last.pt."),
    set_: list[str] = typer.Option([], "--set", help="Override a config value: section.key=value (e.g. train.lr=3e-4). Repeatable."),
    sample: Path | None = typer.Option(None, "--sample", help="After training, generate the target video of one pair and write it here (mp4)."),
    pair: str = typer.Option("0", "--pair", help="Pair to sample: its index in the build or its pair_id."),
    sample_steps: int | None = typer.Option(None, "--sample-steps", min=1, help="Euler steps of the sampler (default: sample.steps)."),
    model: str = typer.Option("reference", "--model", help="reference (default): the small stand-in model; wan: ReCamDriving on Wan2.1 (configs wan-<name> in stages/train/)."),
    transformer: Path | None = typer.Option(None, "--transformer", help="--model wan: the Wan2.1-T2V-1.3B diffusers folder (or its transformer/); sets model.transformer."),
    vae: Path | None = typer.Option(None, "--vae", help="--model wan: the Wan2.1 VAE folder (or the whole diffusers folder), to encode a pixel build and decode samples; sets model.vae."),
    text_encoder: Path | None = typer.Option(None, "--text-encoder", help="--model wan: the umT5 folder (or the whole diffusers folder) for the empty prompt's embedding; sets model.text_encoder."),
    sample_set: Path | None = typer.Option(None, "--sample-set", help="With --sample FOLDER: generate every row of this inference set (paradrive build --kind inference) into FOLDER/<pair_id>.mp4, as 'paradrive eval --build' scores them."),
) -> None:
    """Train the ReCamDriving-style model on a build's pairs (resumes a run left in --out).

    On several GPUs: torchrun --nproc_per_node N --no-python paradrive train ... (data parallel;
    rank 0 writes the run folder and prints)."""
    from paradrive.train.distributed import leave

    try:
        _train(build, stage, config, out_dir, steps, init, set_, sample, pair, sample_steps, model,
               {"transformer": transformer, "vae": vae, "text_encoder": text_encoder}, sample_set)
    finally:
        leave()


def _train(build: Path, stage: int, config: str | None, out_dir: Path | None, steps: int | None,
           init: Path | None, set_: list[str], sample: Path | None, pair: str, sample_steps: int | None,
           model: str, folders: dict[str, Path | None], sample_set: Path | None) -> None:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from paradrive.train.trainer import parse_set

    notes: list[str] = []
    try:
        cfg = _load_config(model, config, parse_set(set_), folders)
        if not build.is_dir():
            raise FileNotFoundError(f"--build {build}: no such build folder (run 'paradrive build' first)")
        run_dir = out_dir if out_dir is not None else Path("runs") / build.resolve().name
        stage_dir = run_dir / f"stage{stage}"
        if stage == 2 and init is None and not (stage_dir / "last.pt").exists():
            init = run_dir / "stage1" / "last.pt"
            if not init.exists():
                raise FileNotFoundError(f"stage 2 needs stage-1 weights: none at {init}; run "
                                        f"'paradrive train --stage 1' with the same --out, or pass --init")
        dataset = _open_dataset(model, build, cfg, notes)
        trainer = _trainer_class(model)(cfg, stage, stage_dir, dataset, init=init)
    except (ValueError, FileNotFoundError, TypeError, ParaDriveError) as exc:
        _fail(str(exc))
    if not trainer.world.main:   # rank 0 alone prints, writes and samples
        _run(trainer, int(cfg["train"]["steps"] if steps is None else steps))
        return
    for line in notes + trainer.notes:
        console.print(f"[yellow]note:[/] {escape(line)}", soft_wrap=True)

    total = int(cfg["train"]["steps"] if steps is None else steps)
    progress = Progress(TextColumn("[bold]stage {task.fields[stage]}"), BarColumn(), MofNCompleteColumn(),
                        TextColumn("loss {task.fields[loss]}"), TimeElapsedColumn(), console=console,
                        disable=not console.is_terminal)
    with progress:
        task = progress.add_task("train", total=total, completed=min(trainer.step, total), stage=stage, loss="-")
        losses = _run(trainer, total, on_step=lambda s, l: progress.update(task, completed=s, loss=f"{l:.4f}"))
    if losses:
        k = max(1, min(10, len(losses) // 4))
        first, last = sum(losses[:k]) / k, sum(losses[-k:]) / k
        typer.echo(f"stage {stage}: {len(losses)} steps to step {trainer.step}; loss {first:.4f} -> {last:.4f} "
                  f"(mean of first / last {k}); {trainer.world.world_size} process(es); checkpoint "
                  f"{stage_dir / 'last.pt'}")
    else:
        typer.echo(f"stage {stage}: already at step {trainer.step} (of {total}); checkpoint {stage_dir / 'last.pt'}")

    if sample is not None:
        from paradrive.train.trainer import sample_video, torch_threads, write_video
        from paradrive.train.wan import WanTrainer

        try:
            if sample_set is not None:
                items = _open_dataset(model, sample_set, cfg)
                # a pair id names the file; one from a shared build must stay inside the folder
                picks = [(functools.partial(items.__getitem__, i),
                          path_inside(sample, f"{pid}.mp4", f"{sample_set}: pair {pid}"))
                         for i, pid in enumerate(items.pair_ids)]
            else:
                item = _find_pair(dataset, pair)
                picks = [(functools.partial(dict, item), sample)]
        except (ValueError, IndexError, ParaDriveError) as exc:
            _fail(str(exc))
        s = cfg["sample"]
        trainer.model.eval()
        for load, path in picks:
            item = load()
            with torch_threads(cfg["threads"]):
                if isinstance(trainer, WanTrainer):   # decodes through the VAE
                    video = trainer.sample(item, sample_steps or int(s["steps"]), seed=int(s["seed"]))
                else:
                    video = sample_video(trainer.model, trainer.encoder, item,
                                         sample_steps or int(s["steps"]), seed=int(s["seed"]),
                                         shift=float(cfg["flow"]["shift"]))
            path.parent.mkdir(parents=True, exist_ok=True)
            write_video(path, video, float(s["fps"]))
            typer.echo(f"sample of {item['pair_id']} ({video.shape[0]} frames, offset "
                       f"{item['offset_m']} m) -> {path}")


def _run(trainer, total: int, on_step=None) -> list[float]:
    """``trainer.train``; a failure of a step (a loss that is not finite, a pair that cannot be
    read) is one line, exit 1: the run resumes from its last checkpoint once fixed."""
    try:
        return trainer.train(total, on_step=on_step)
    except (FloatingPointError, ParaDriveError) as exc:
        console.print(f"[bold red]error:[/] stage {trainer.stage} stopped at step {trainer.step}: {escape(str(exc))}; "
                      f"a re-run resumes from {trainer.out_dir / 'last.pt'}", soft_wrap=True)
        raise typer.Exit(EXIT_FAILED) from None


def _load_config(model: str, config: str | None, overrides: dict, folders: dict[str, Path | None]) -> dict:
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


def _open_dataset(model: str, build: Path, cfg: dict, notes: list[str] | None = None):
    """The build's pairs as ``--model``'s trainer reads them (``notes``: what a user should know
    of how, e.g. a latent cache that does not fit)."""
    if model == "wan":
        from paradrive.train.wan import open_wan_dataset

        return open_wan_dataset(build, cfg, notes)
    from paradrive.train.trainer import open_dataset

    return open_dataset(build, cfg)


def _trainer_class(model: str) -> type:
    from paradrive.train.trainer import Trainer

    if model == "wan":
        from paradrive.train.wan import WanTrainer

        return WanTrainer
    return Trainer


def _find_pair(dataset, pair: str) -> dict:
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


def register(app: typer.Typer) -> None:
    """Add ``paradrive train`` to the command line."""
    app.command("train")(train)
