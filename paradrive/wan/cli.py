"""The Wan2.1 commands. ``paradrive encode BUILD --vae DIR``: a published build's Wan2.1 latent
cache, outside a build run, by the same code as the ``encode`` stage
(:func:`paradrive.wan.encode.encode_build`), with the stage's parameters from
``stages/encode.yaml``, a profile and ``--set``. ``paradrive convert FORMAT BUILD OUT``: a build
in the layout of ReCamMaster's, DiffSynth-Studio's or diffusers' trainers
(:mod:`paradrive.train.convert`). ``paradrive generate --build B --checkpoint RUN/stage2 --out DIR``:
a trained model's videos of an inference build (:mod:`paradrive.wan.generate`). Each imports
torch and diffusers only when it runs."""

from __future__ import annotations

from pathlib import Path

__all__ = ["register"]


def register(app) -> None:
    """Add ``paradrive encode``, ``paradrive convert`` and ``paradrive generate`` to the command line."""
    _register_encode(app)
    _register_convert(app)
    _register_generate(app)


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
        except (ParaDriveError, OSError) as exc:   # OSError: a write failed on the way (disk full, ...)
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
        out: Path = typer.Argument(..., metavar="OUT", help=(
            "The folder to write: created whole when the export is complete (an earlier export there is replaced).")),
        vae: Path | None = typer.Option(
            None, "--vae", help="recammaster (required): a Wan2.1 VAE folder, for each video's <video>.tensors.pth."),
        text_encoder: Path | None = typer.Option(
            None, "--text-encoder", help="recammaster: the umT5 folder (the empty prompt's embedding)."),
        device: str | None = typer.Option(
            None, "--device", help="recammaster: where the VAE and umT5 run: auto, cpu, cuda[:n] (encode.device)."),
        num_frames: int | None = typer.Option(
            None, "--num-frames", min=1, help="pixels: frames per video (default: the whole clip)."),
        limit: int | None = typer.Option(
            None, "--limit", min=1, help="Only the first N pairs (in pair_id order): a quick look at the layout."),
    ) -> None:
        """Hand a build to another trainer: ReCamMaster's, DiffSynth-Studio's or diffusers' layout."""
        from rich.console import Console
        from rich.markup import escape

        from paradrive.errors import EXIT_FAILED, EXIT_USAGE, ConfigError, ParaDriveError
        from paradrive.train.convert import convert_build

        err = Console(stderr=True)
        try:
            count = convert_build(fmt, build, out, vae=vae, text_encoder=text_encoder,
                                  num_frames=num_frames, limit=limit, device=device)
        except (ValueError, FileNotFoundError, ConfigError) as exc:
            err.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
            raise typer.Exit(EXIT_USAGE) from None
        except ParaDriveError as exc:
            err.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
            raise typer.Exit(EXIT_FAILED) from None
        except OSError as exc:   # a full disk, a file-size limit, a folder that went away
            err.print(f"[bold red]error:[/] {escape(write_failure(out, exc))}", soft_wrap=True)
            raise typer.Exit(EXIT_FAILED) from None
        typer.echo(f"{count} pairs of {build} -> {out} ({fmt})")


def write_failure(out: Path, exc: OSError) -> str:
    """One line for an export that could not be written (nothing of it was kept)."""
    why = exc.strerror or str(exc)
    where = f" ({exc.filename})" if exc.filename else ""
    return (f"could not write the export into {out}: {why}{where}; nothing of it was kept: free space (or raise "
            f"the file-size limit) where {out} is, or pass another OUT")


def _register_generate(app) -> None:
    import typer

    @app.command("generate")
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
        from rich.console import Console
        from rich.markup import escape

        from paradrive.errors import EXIT_FAILED, EXIT_PARTIAL, EXIT_USAGE, ParaDriveError
        from paradrive.wan.generate import generate, load_generator

        err = Console(stderr=True)
        folders = {"transformer": transformer, "vae": vae, "text_encoder": text_encoder}
        try:
            generator = load_generator(checkpoint, {k: str(v) if v else None for k, v in folders.items()}, device)
            report = generate(build, generator, out, steps, limit)
        except (ValueError, FileNotFoundError, ParaDriveError) as exc:
            err.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
            raise typer.Exit(EXIT_USAGE) from None
        for line in report.notes:
            err.print(f"[yellow]note:[/] {escape(line)}", soft_wrap=True)
        for line in report.failed:
            err.print(f"[bold red]failed:[/] {escape(line)}", soft_wrap=True)
        typer.echo(f"{len(report.written)} videos of {build} -> {out} (stage {generator.stage}); "
                   f"score them with: paradrive eval --build {build} --videos {out}")
        if report.failed:
            raise typer.Exit(EXIT_PARTIAL if report.written else EXIT_FAILED)
