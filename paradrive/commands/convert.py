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
    vae: str | None = typer.Option(
        None, "--vae", help="recammaster: a Wan2.1 VAE folder (or 'tiny', the smoke config's) for each video's <video>.tensors.pth; not needed when the build's latent cache fits (480x832, cropped, enough frames)."),
    text_encoder: Path | None = typer.Option(
        None, "--text-encoder", help="recammaster: the folder with umT5 in text_encoder/ and tokenizer/, for the empty prompt's embedding (default: the --vae folder, as paradrive encode)."),
    device: str | None = typer.Option(
        None, "--device", help="recammaster: where the VAE and umT5 run: auto, cpu, cuda[:n] (encode.device)."),
    num_frames: int | None = typer.Option(
        None, "--num-frames", min=1, help="pixels: frames per video (default: the whole clip); recammaster: frames encoded, 4k + 1 (default 81, the frames its loader reads cameras for)."),
    size: str | None = typer.Option(
        None, "--size", metavar="HxW", help="pixels: frame size (default: as stored); recammaster: only 480x832, the grid its DiT reads (the default)."),
    limit: int | None = typer.Option(
        None, "--limit", min=1, help="Only the first N pairs (in pair_id order): a quick look at the layout."),
) -> None:
    """Hand a build to another trainer: ReCamMaster's, DiffSynth-Studio's or diffusers' layout."""
    from paradrive.train.convert import convert_build

    notes: list[str] = []
    try:
        counts = convert_build(fmt, build, out, vae=vae, text_encoder=text_encoder, num_frames=num_frames,
                               size=parse_size(size), limit=limit, device=device, notes=notes)
    except (ValueError, FileNotFoundError, ConfigError) as exc:
        fail(str(exc), EXIT_USAGE)
    except ParaDriveError as exc:
        fail(str(exc), EXIT_FAILED)
    except OSError as exc:   # a full disk, a file-size limit, a folder that went away
        fail(write_failure(out, exc), EXIT_FAILED)
    for note in notes:
        typer.echo(f"note: {note}", err=True)
    line = f"{counts['pairs']} pairs of {build} -> {out} ({fmt})"
    if "videos" in counts:
        line += (f": {counts['videos']} distinct videos' latents ({counts['encoded']} encoded, "
                 f"{counts['from_cache']} from the build's latent cache), {counts['bytes'] / 1e6:.1f} MB, "
                 f"linked into each pair")
    typer.echo(line)


def parse_size(text: str | None) -> tuple[int, int] | None:
    """``HxW`` as (H, W); ValueError in one line otherwise."""
    if text is None:
        return None
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() and int(p) > 0 for p in parts):
        fail(f"--size {text}: write it as HxW, e.g. 480x832", EXIT_USAGE)
    return int(parts[0]), int(parts[1])


def write_failure(out: Path, exc: OSError) -> str:
    """One line for an export that could not be written (nothing of it was kept)."""
    why = exc.strerror or str(exc)
    where = f" ({exc.filename})" if exc.filename else ""
    return (f"could not write the export into {out}: {why}{where}; nothing of it was kept: free space (or raise "
            f"the file-size limit) where {out} is, or pass another OUT")


def register(app: typer.Typer) -> None:
    """Add ``paradrive convert`` to the command line."""
    app.command("convert")(convert_cmd)
