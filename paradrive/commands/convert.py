"""``paradrive convert FORMAT BUILD OUT``: a build in the layout of ReCamMaster's,
DiffSynth-Studio's or diffusers' trainers (:mod:`paradrive.train.convert`). Imports torch and
diffusers only when it runs."""

from __future__ import annotations

from pathlib import Path

import typer

from paradrive.commands.common import fail
from paradrive.errors import EXIT_FAILED, EXIT_USAGE, ConfigError, ParaDriveError


def convert_cmd(
    fmt: str = typer.Argument(..., metavar="FORMAT", help="recammaster, diffsynth or pixels."),
    build: Path = typer.Argument(..., metavar="BUILD", help="A build folder (<manifests>/<build>)."),
    out: Path = typer.Argument(..., metavar="OUT", help=(
        "The folder to write: created whole when the export is complete (an earlier export there is replaced).")),
    vae: Path | None = typer.Option(
        None, "--vae", help="recammaster (required): a Wan2.1 VAE folder, for each video's <video>.tensors.pth."),
    text_encoder: Path | None = typer.Option(
        None, "--text-encoder", help="recammaster: the folder with umT5 in text_encoder/ and tokenizer/, for the empty prompt's embedding (default: the --vae folder, as paradrive encode)."),
    device: str | None = typer.Option(
        None, "--device", help="recammaster: where the VAE and umT5 run: auto, cpu, cuda[:n] (encode.device)."),
    num_frames: int | None = typer.Option(
        None, "--num-frames", min=1, help="pixels: frames per video (default: the whole clip)."),
    limit: int | None = typer.Option(
        None, "--limit", min=1, help="Only the first N pairs (in pair_id order): a quick look at the layout."),
) -> None:
    """Hand a build to another trainer: ReCamMaster's, DiffSynth-Studio's or diffusers' layout."""
    from paradrive.train.convert import convert_build

    try:
        count = convert_build(fmt, build, out, vae=vae, text_encoder=text_encoder,
                              num_frames=num_frames, limit=limit, device=device)
    except (ValueError, FileNotFoundError, ConfigError) as exc:
        fail(str(exc), EXIT_USAGE)
    except ParaDriveError as exc:
        fail(str(exc), EXIT_FAILED)
    except OSError as exc:   # a full disk, a file-size limit, a folder that went away
        fail(write_failure(out, exc), EXIT_FAILED)
    typer.echo(f"{count} pairs of {build} -> {out} ({fmt})")


def write_failure(out: Path, exc: OSError) -> str:
    """One line for an export that could not be written (nothing of it was kept)."""
    why = exc.strerror or str(exc)
    where = f" ({exc.filename})" if exc.filename else ""
    return (f"could not write the export into {out}: {why}{where}; nothing of it was kept: free space (or raise "
            f"the file-size limit) where {out} is, or pass another OUT")


def register(app: typer.Typer) -> None:
    """Add ``paradrive convert`` to the command line."""
    app.command("convert")(convert_cmd)
