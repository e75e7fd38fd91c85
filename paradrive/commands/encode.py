"""``paradrive encode BUILD --vae DIR``: a published build's Wan2.1 latent cache, outside a build
run, by the same code as the ``encode`` stage (:func:`paradrive.wan.encode.encode_build`), with
the stage's parameters from ``stages/encode.yaml``, a profile and ``--set``. Imports torch and
diffusers only when it runs."""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from paradrive.commands.common import fail
from paradrive.errors import EXIT_FAILED, EXIT_USAGE, ConfigError, ParaDriveError
from paradrive.io import no_room_message


def encode_cmd(
    build: Path = typer.Argument(..., help="The build folder (<manifests>/<build>, holding index.json)."),
    vae: str | None = typer.Option(None, "--vae", help=(
        "Local folder with Wan2.1's VAE (its vae/ folder or the whole diffusers folder), or 'tiny' (the smoke training config's); sets encode.vae.")),
    text_encoder: str | None = typer.Option(None, "--text-encoder", help=(
        "Local folder with umT5 in text_encoder/ and tokenizer/ (default: the --vae folder); "
        "sets encode.text_encoder.")),
    device: str | None = typer.Option(None, "--device", help=(
        "auto (CUDA when present), cpu, cuda or cuda:<n>; sets encode.device.")),
    profile: str | None = typer.Option(None, "--profile", help=(
        "Stage profile whose encode values apply (default: the paper's).")),
    set_: list[str] = typer.Option([], "--set", help=(
        "Override an encode parameter: encode.key=value (e.g. encode.size=null). Repeatable.")),
) -> None:
    """Encode a build's pairs with Wan2.1's VAE and the empty prompt with umT5 into <build>/latents/."""
    from paradrive.contracts.specs import StageRegistry, parse_overrides
    from paradrive.wan.encode import encode_build

    try:
        overrides = parse_overrides(set_)
        unknown = sorted(set(overrides) - {"encode"})
        if unknown:
            raise ConfigError(f"--set {unknown[0]}.…: paradrive encode takes encode.<param> only")
        given = {"vae": vae, "text_encoder": text_encoder, "device": device}
        overrides.setdefault("encode", {}).update({k: v for k, v in given.items() if v is not None})
        config = StageRegistry().resolve(profile, overrides)
        config.check(["encode"])
        settings = config.typed("encode").settings()
    except ConfigError as exc:
        fail(str(exc), EXIT_USAGE)
    logging.getLogger("paradrive.encode").setLevel(logging.INFO)
    try:
        doc = encode_build(build, settings)
    except ConfigError as exc:
        fail(str(exc), EXIT_USAGE)
    except (ParaDriveError, OSError) as exc:   # OSError: a write failed on the way (disk full, ...)
        fail(no_room_message(exc, f"build {build.name}: encode", elsewhere="encode a copy of the "
                             "build on a disk with room") or str(exc), EXIT_FAILED)
    totals = doc["totals"]
    typer.echo(f"encoded {totals['pairs']} pairs ({totals['videos']} videos, {len(doc['shards'])} shards, "
               f"{totals['bytes'] / 1e6:.1f} MB, latents {doc['latent_shape']} {doc['dtype']}) into "
               f"{build / 'latents'}")


def register(app: typer.Typer) -> None:
    """Add ``paradrive encode`` to the command line."""
    app.command("encode")(encode_cmd)
