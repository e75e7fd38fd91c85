"""``paradrive view TARGET``: a scene or a build's pairs as a Rerun recording
(:mod:`paradrive.view`)."""

from __future__ import annotations

from pathlib import Path

import typer

from paradrive.commands.common import DEFAULT_DATA, console, fail, out
from paradrive.errors import EXIT_FAILED, ConfigError, ParaDriveError


def view_cmd(
    target: str = typer.Argument(..., help="A scene folder (<data>/scenes/<id>) or scene URI after ingest, or a build folder (<manifests>/<build>)."),
    data: Path = typer.Option(DEFAULT_DATA, "--data", help="Where a scene URI's folder is (<data>/scenes/<scene_id>)."),
    pair: list[str] = typer.Option([], "--pair", help="A build: show this pair (its pair_id); repeatable. Default: the build's first pairs by pair id."),
    save: Path | None = typer.Option(None, "--save", help="Write the recording (.rrd) here; default: beside the scene or build folder, <folder>.rrd."),
    spawn: bool = typer.Option(False, "--spawn", help="Then open it in the Rerun viewer (needs a display; else run `rerun FILE.rrd` where there is one)."),
) -> None:
    """Write a scene (cameras, LiDAR, actors, the fit's Gaussians, renders and clips) or a build's
    pairs (source, condition and target videos, both cameras, scores) as a Rerun recording."""
    from paradrive import view
    from paradrive.io import check_output

    try:
        kind, folder = view.resolve_target(target, data)
        if pair and kind != "build":
            raise ConfigError(f"--pair picks pairs of a build; {folder} is a scene folder")
        out_file = check_output(save or view.default_output(folder), "--save")
        report = view.view_build(folder, out_file, pair_ids=pair) if kind == "build" else view.view_scene(folder, out_file)
        out.print(view.describe(report), markup=False, highlight=False, soft_wrap=True)
        for line in report.left_out:
            console.print(f"left out: {line}", markup=False, highlight=False, soft_wrap=True)
        if spawn:
            view.open_viewer(report.path)
    except ConfigError as exc:
        fail(str(exc))
    except (ParaDriveError, OSError) as exc:   # OSError: the write failed at the end (disk full, ...)
        fail(str(exc), EXIT_FAILED)


def register(app: typer.Typer) -> None:
    """Add ``paradrive view`` to the command line."""
    app.command("view")(view_cmd)
