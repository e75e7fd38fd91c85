"""``paradrive generate --build B --checkpoint RUN/stage2 --out DIR``: a trained model's videos
of an inference build (:mod:`paradrive.train.generate`). Imports torch and diffusers only when it
runs."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.markup import escape

from paradrive.commands.common import console, fail, note
from paradrive.errors import EXIT_FAILED, EXIT_PARTIAL, EXIT_USAGE, ParaDriveError


def generate_cmd(
    build: Path = typer.Option(..., "--build", help="An inference build (paradrive build --kind inference)."),
    checkpoint: Path = typer.Option(..., "--checkpoint", help=(
        "A stage folder of 'paradrive train --model wan' (e.g. runs/<build>/stage2) or its last.pt.")),
    out: Path = typer.Option(..., "--out", help="Folder for the videos, <pair_id>.mp4 (paradrive eval --videos)."),
    steps: int | None = typer.Option(None, "--steps", min=1, help="Euler steps of the sampler (sample.steps)."),
    transformer: Path | None = typer.Option(None, "--transformer", help=(
        "The base transformer folder (default: the one the checkpoint was trained on).")),
    vae: Path | None = typer.Option(None, "--vae", help="The Wan2.1 VAE folder (default: the run's model.vae)."),
    text_encoder: Path | None = typer.Option(None, "--text-encoder", help=(
        "The umT5 folder (default: the run's model.text_encoder).")),
    device: str | None = typer.Option(None, "--device", help="auto, cpu, cuda or cuda:<n> (default: the run's)."),
    limit: int | None = typer.Option(None, "--limit", min=1, help="Only the first N rows (in pair_id order)."),
) -> None:
    """Generate each row's novel-trajectory video of an inference build with a trained model."""
    from paradrive.train.generate import generate, load_generator

    folders = {"transformer": transformer, "vae": vae, "text_encoder": text_encoder}
    try:
        generator = load_generator(checkpoint, {k: str(v) if v else None for k, v in folders.items()}, device)
        report = generate(build, generator, out, steps, limit)
    except (ValueError, FileNotFoundError, ParaDriveError) as exc:
        fail(str(exc), EXIT_USAGE)
    for line in report.notes:
        note(line)
    for line in report.failed:
        console.print(f"[bold red]failed:[/] {escape(line)}", soft_wrap=True)
    typer.echo(f"{len(report.written)} videos of {build} -> {out} (stage {generator.stage}); "
               f"score them with: paradrive eval --build {build} --videos {out}")
    if report.failed:
        raise typer.Exit(EXIT_PARTIAL if report.written else EXIT_FAILED)


def register(app: typer.Typer) -> None:
    """Add ``paradrive generate`` to the command line."""
    app.command("generate")(generate_cmd)
