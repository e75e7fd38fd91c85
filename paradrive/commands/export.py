"""``paradrive export FORMAT OUT``: a synthetic scene written as a real log (known answers), and
the URI that ingests it."""

from __future__ import annotations

from pathlib import Path

import typer

from paradrive.commands.common import DEFAULT_SCENE, fail
from paradrive.errors import EXIT_FAILED, ConfigError


def export_cmd(
    fmt: str = typer.Argument(..., help="waymo, nuscenes, drivestudio or video (the front camera as a plain MP4)"),
    out: Path = typer.Argument(..., help="Folder to write the log into."),
    scene: str = typer.Option(DEFAULT_SCENE, "--scene", help="A synthetic scene URI."),
    profile: str = typer.Option(None, "--profile", "-p", help="Profile whose ingest.synthetic_* sizes and cameras apply."),
    set_: list[str] = typer.Option([], "--set", help="Override an ingest parameter: ingest.param=value (e.g. ingest.cameras=[front]). Repeatable."),
    with_intrinsics: bool = typer.Option(True, "--with-intrinsics/--without-intrinsics", help="video: put the camera's intrinsics in the printed URI (without them SfM estimates them)."),
) -> None:
    """Write a synthetic scene as a real log (known answers) and print the URI that ingests it.

    The log carries the cameras its ingest keeps with these parameters (ingest.cameras); a video
    carries the front camera only."""
    from paradrive.errors import SceneError
    from paradrive.ingest.export import export_scene
    from paradrive.io import check_output
    from paradrive.pipeline import StageRegistry, parse_overrides

    try:
        params = StageRegistry().resolve(profile, parse_overrides(set_)).typed("ingest")
        check_output(out, "export: OUT", folder=True)   # a file, a device, a place not writable: before any work
    except ConfigError as exc:
        fail(str(exc))
    before = set(out.rglob("*")) if out.is_dir() else None
    try:
        print(export_scene(scene, fmt, out, params, with_intrinsics=with_intrinsics))
    except (ValueError, SceneError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2)
    except OSError as exc:   # the write failed on the way (disk full, file size limit, ...)
        _remove_new(out, before)
        fail(str(exc), EXIT_FAILED)


def _remove_new(out: Path, before: set[Path] | None) -> None:
    """What a failed export wrote under ``out``: all of it when ``out`` was not there before
    (``before`` None), else the entries not in ``before``, so no part of a log is left."""
    import shutil

    from paradrive.io import remove_entry

    if before is None:
        shutil.rmtree(out, ignore_errors=True)
        return
    for path in sorted(set(out.rglob("*")) - before, key=lambda p: len(p.parts), reverse=True):
        remove_entry(path)


def register(app: typer.Typer) -> None:
    """Add ``paradrive export`` to the command line."""
    app.command("export")(export_cmd)
