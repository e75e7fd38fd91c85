"""``paradrive train``: train stage 1 or 2 of the reference model (or ReCamDriving on Wan2.1) on a
build, and write samples (:mod:`paradrive.train.runs` sets the run up)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from paradrive.commands.common import console, fail, note
from paradrive.errors import EXIT_FAILED, ParaDriveError

if TYPE_CHECKING:  # torch: imported when the command runs
    from paradrive.train.runs import Run


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
    from paradrive.train.runs import start_run
    from paradrive.train.trainer import parse_set

    try:
        run = start_run(build, stage, config, out_dir, init, parse_set(set_), model, folders)
    except (ValueError, FileNotFoundError, TypeError, ParaDriveError) as exc:
        fail(str(exc))
    trainer = run.trainer
    total = int(run.cfg["train"]["steps"] if steps is None else steps)
    if not trainer.world.main:   # rank 0 alone prints, writes and samples
        _steps(trainer, total)
        return
    for line in run.notes + trainer.notes:
        note(line)
    progress = Progress(TextColumn("[bold]stage {task.fields[stage]}"), BarColumn(), MofNCompleteColumn(),
                        TextColumn("loss {task.fields[loss]}"), TimeElapsedColumn(), console=console,
                        disable=not console.is_terminal)
    with progress:
        task = progress.add_task("train", total=total, completed=min(trainer.step, total), stage=stage, loss="-")
        losses = _steps(trainer, total, on_step=lambda s, l: progress.update(task, completed=s, loss=f"{l:.4f}"))
    if losses:
        k = max(1, min(10, len(losses) // 4))
        first, last = sum(losses[:k]) / k, sum(losses[-k:]) / k
        typer.echo(f"stage {stage}: {len(losses)} steps to step {trainer.step}; loss {first:.4f} -> {last:.4f} "
                   f"(mean of first / last {k}); {trainer.world.world_size} process(es); checkpoint "
                   f"{run.stage_dir / 'last.pt'}")
    else:
        typer.echo(f"stage {stage}: already at step {trainer.step} (of {total}); checkpoint {run.stage_dir / 'last.pt'}")
    if sample is not None:
        _samples(run, model, sample, pair, sample_set, sample_steps)


def _steps(trainer, total: int, on_step=None) -> list[float]:
    """``trainer.train``; a failure of a step (a loss that is not finite, a pair that cannot be
    read) is one line, exit 1: the run resumes from its last checkpoint once fixed."""
    try:
        return trainer.train(total, on_step=on_step)
    except (FloatingPointError, ParaDriveError) as exc:
        console.print(f"[bold red]error:[/] stage {trainer.stage} stopped at step {trainer.step}: {escape(str(exc))}; "
                      f"a re-run resumes from {trainer.out_dir / 'last.pt'}", soft_wrap=True)
        raise typer.Exit(EXIT_FAILED) from None


def _samples(run: Run, model: str, sample: Path, pair: str, sample_set: Path | None,
             steps: int | None) -> None:
    """``--sample``: the trained model's video of one pair, or of every row of ``--sample-set``."""
    from paradrive.train.runs import sample_picks, write_sample

    try:
        picks = sample_picks(run, model, sample, pair, sample_set)
    except (ValueError, IndexError, ParaDriveError) as exc:
        fail(str(exc))
    for load, path in picks:
        item = load()
        frames = write_sample(run, item, path, steps)
        typer.echo(f"sample of {item['pair_id']} ({frames} frames, offset "
                   f"{item['offset_m']} m) -> {path}")


def register(app: typer.Typer) -> None:
    """Add ``paradrive train`` to the command line."""
    app.command("train")(train)
