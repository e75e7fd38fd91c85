"""The Wan2.1 commands. ``paradrive encode BUILD --vae DIR``: a published build's Wan2.1 latent
cache, outside a build run, by the same code as the ``encode`` stage
(:func:`paradrive.wan.encode.encode_build`), with the stage's parameters from
``stages/encode.yaml``, a profile and ``--set``. ``paradrive convert FORMAT BUILD OUT``: a build
in the layout of ReCamMaster's, DiffSynth-Studio's or diffusers' trainers
(:mod:`paradrive.train.convert`). Both import torch and diffusers only when they run."""

from __future__ import annotations

from pathlib import Path

__all__ = ["register"]


def register(app) -> None:
    """Add ``paradrive encode`` and ``paradrive convert`` to the command line."""
    _register_encode(app)
    _register_convert(app)


def _register_encode(app) -> None:
    import typer

    @app.command("encode")
    def encode_cmd(
        build: Path = typer.Argument(..., help="The build folder (<manifests>/<build>, holding index.json)."),
        vae: str | None = typer.Option(None, "--vae", help=(
            "Local folder with Wan2.1's VAE (its vae/ folder or the whole diffusers folder); sets encode.vae.")),
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
        import logging

        from rich.console import Console
        from rich.markup import escape

        from paradrive.errors import EXIT_FAILED, EXIT_USAGE, ConfigError, ParaDriveError
        from paradrive.contracts.specs import StageRegistry, parse_overrides
        from paradrive.wan.encode import encode_build

        err = Console(stderr=True)
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
            err.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
            raise typer.Exit(EXIT_USAGE) from None
        logging.getLogger("paradrive.encode").setLevel(logging.INFO)
        try:
            doc = encode_build(build, settings)
        except ConfigError as exc:
            err.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
            raise typer.Exit(EXIT_USAGE) from None
        except ParaDriveError as exc:
            err.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
            raise typer.Exit(EXIT_FAILED) from None
        totals = doc["totals"]
        typer.echo(f"encoded {totals['pairs']} pairs ({totals['videos']} videos, {len(doc['shards'])} shards, "
                   f"{totals['bytes'] / 1e6:.1f} MB, latents {doc['latent_shape']} {doc['dtype']}) into "
                   f"{build / 'latents'}")



def _register_convert(app) -> None:
    import typer

    @app.command("convert")
    def convert_cmd(
        fmt: str = typer.Argument(..., metavar="FORMAT", help="recammaster, diffsynth or pixels."),
        build: Path = typer.Argument(..., metavar="BUILD", help="A build folder (<manifests>/<build>)."),
        out: Path = typer.Argument(..., metavar="OUT", help="The folder to write (created; files in it are replaced)."),
        vae: Path | None = typer.Option(
            None, "--vae", help="recammaster: a Wan2.1 VAE folder, to write each video's <video>.tensors.pth too."),
        text_encoder: Path | None = typer.Option(
            None, "--text-encoder", help="recammaster with --vae: the umT5 folder (the empty prompt's embedding)."),
        num_frames: int | None = typer.Option(
            None, "--num-frames", min=1, help="pixels: frames per video (default: the whole clip)."),
        limit: int | None = typer.Option(
            None, "--limit", min=1, help="Only the first N pairs (in pair_id order): a quick look at the layout."),
    ) -> None:
        """Hand a build to another trainer: ReCamMaster's, DiffSynth-Studio's or diffusers' layout."""
        from rich.console import Console
        from rich.markup import escape

        from paradrive.errors import ConfigError, ParaDriveError
        from paradrive.train.convert import convert_build

        try:
            count = convert_build(fmt, build, out, vae=vae, text_encoder=text_encoder,
                                  num_frames=num_frames, limit=limit)
        except (ValueError, FileNotFoundError, ConfigError, ParaDriveError) as exc:
            Console(stderr=True).print(f"[bold red]error:[/] {escape(str(exc))}")
            raise typer.Exit(2) from exc
        typer.echo(f"{count} pairs of {build} -> {out} ({fmt})")
