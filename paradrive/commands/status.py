"""``paradrive status BUILD``: what the ledger of a build says, for a person or (``--json``) a
script: scenes done / failed / running / pending, time and memory per stage, the slowest scenes,
every failure with its reason, the scenes locked now and by which build, and the locks the build
took over (:func:`paradrive.pipeline.status.build_status` gathers them)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import typer
from rich import box
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from paradrive.commands.common import DEFAULT_MANIFESTS, fail, new_console
from paradrive.errors import ParaDriveError

STATE_STYLE = {"done": "green", "skipped": "green", "failed": "red", "blocked": "yellow",
               "running": "cyan", "pending": "dim"}


def _when(ts: float | None) -> str:
    return dt.datetime.fromtimestamp(ts).strftime("%Y-%m-%d %H:%M:%S") if ts else "-"


def _secs(value: float | None) -> str:
    if not value:
        return "-"
    if value >= 3600:
        return f"{value / 3600:.1f}h"
    if value >= 60:
        return f"{value / 60:.1f}m"
    return f"{value:.1f}s"


def print_status(summary: dict, console: Console, *, all_scenes: bool = False) -> None:
    """The summary of :func:`paradrive.pipeline.status.build_status` on ``console``: the last
    run, the counts, the stages, the slowest scenes (every scene's states with ``all_scenes``),
    the failures, the locks held and taken over, and the build stages."""
    counts = summary["counts"]
    run = summary["last_run"]
    if run:
        finished = (f"finished {_when(run['finished_at'])}, exit code {run['exit_code']}"
                    if run["finished_at"] else "still running (or was killed)")
        console.print(f"build [bold]{escape(summary['build'])}[/] — last run started "
                      f"{_when(run['started_at'])} ({run['executor'] or '?'} executor), {finished}")
    console.print(f"ledger: {summary['ledger']}", markup=False)
    console.print(f"[bold]{summary['scenes']}[/] scenes: [green]{counts['done']} done[/], "
                  f"[red]{counts['failed']} failed[/], [cyan]{counts['running']} running[/], "
                  f"{counts['pending']} pending")
    console.print(_stage_table(summary))

    slow = [s for s in summary["slowest"] if s["seconds"] > 0][:5]
    if slow:
        table = Table(title="slowest scenes", title_justify="left", box=box.SIMPLE_HEAD)
        table.add_column("scene")
        table.add_column("time", justify="right")
        table.add_column("state")
        for s in slow:
            table.add_row(escape(s["scene_id"]), _secs(s["seconds"]),
                          f"[{STATE_STYLE[s['state']]}]{s['state']}")
        console.print(table)

    if all_scenes:
        console.print(_scene_table(summary))

    if summary["failures"]:
        table = Table(title="failures", title_justify="left", box=box.SIMPLE_HEAD)
        table.add_column("scene")
        table.add_column("stage")
        table.add_column("attempts", justify="right")
        table.add_column("reason", overflow="fold")
        for f in summary["failures"]:
            table.add_row(escape(f["scene_id"]), f["stage"], str(f["attempts"]), escape(f["error"]))
        console.print(table)
        console.print(f"retry them: paradrive build --build {summary['build']} --retry-failed "
                      f"(with the same --data, --manifests and --profile)", markup=False)
    if summary.get("locks"):
        table = Table(title="locked scenes [dim](a stage of them runs now)[/]", title_justify="left",
                      box=box.SIMPLE_HEAD)
        table.add_column("scene")
        table.add_column("held by", overflow="fold")
        for lock in summary["locks"]:
            table.add_row(escape(lock["scene_id"]), escape(lock["holder"]))
        console.print(table)
    if summary.get("locks_error"):
        console.print(f"[yellow]locks not shown:[/] {escape(summary['locks_error'])}")
    for t in summary.get("takeovers", []):
        console.print(f"[yellow]{escape(t['scene_id'])} {t['stage']}[/] at {_when(t['at'])}: {escape(t['error'])}")
    for b in summary["build_stages"]:
        style = STATE_STYLE.get(b["state"], "dim")
        console.print(f"{b['stage']}: [{style}]{b['state']}[/]"
                      + (f" — {escape(b['error'])}" if b["error"] else ""))


def _stage_table(summary: dict) -> Table:
    """Per stage: its states' counts, its seconds (mean, max, total) and peak memory."""
    stages = Table(title="stages [dim](skip: up to date; block: an earlier stage failed; "
                         "MB: peak memory)[/]", title_justify="left", box=box.SIMPLE_HEAD,
                   collapse_padding=True, pad_edge=False)
    stages.add_column("stage", no_wrap=True)
    for col in ("done", "skip", "fail", "block", "run", "wait", "mean", "max", "total", "MB"):
        stages.add_column(col, justify="right", no_wrap=True,
                          min_width=6 if col in ("mean", "max", "total", "MB") else None)
    for st in summary["stages"]:
        stages.add_row(st["stage"], str(st["done"]), str(st["skipped"]),
                       f"[red]{st['failed']}" if st["failed"] else "0",
                       f"[yellow]{st['blocked']}" if st["blocked"] else "0",
                       str(st["running"]), str(st["pending"]), _secs(st["seconds_mean"]),
                       _secs(st["seconds_max"]), _secs(st["seconds_total"]),
                       f"{st['peak_rss_mb_max']:.0f}" if st["peak_rss_mb_max"] else "-")
    return stages


def _scene_table(summary: dict) -> Table:
    """Every scene's state in each scene stage, and its time."""
    table = Table(title="scenes", title_justify="left", box=box.SIMPLE_HEAD)
    table.add_column("scene")
    names = [st["stage"] for st in summary["stages"] if not _is_build_stage(summary, st["stage"])]
    for name in names:
        table.add_column(name)
    table.add_column("time", justify="right")
    for sc in summary["scene_table"]:
        cells = [sc["stages"].get(n, "") for n in names]
        table.add_row(escape(sc["scene_id"]), *[f"[{STATE_STYLE.get(c, 'dim')}]{c}" for c in cells],
                      _secs(sc["seconds"]))
    return table


def _is_build_stage(summary: dict, stage: str) -> bool:
    return any(b["stage"] == stage for b in summary["build_stages"])


def status(
    build: str = typer.Argument(..., help="Build name (under --manifests) or a build folder."),
    manifests: Path = typer.Option(DEFAULT_MANIFESTS, "--manifests", help="Where builds are written."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
    all_scenes: bool = typer.Option(False, "--scenes", help="Also list every scene's stage states."),
    data: str = typer.Option(None, "--data", help="Data root whose scene locks to show (default: the one the build last ran with)."),
    storage_option: list[str] = typer.Option([], "--storage-option", help="fsspec option for a URL data root, KEY=VALUE, as for 'paradrive build'. Repeatable."),
) -> None:
    """Show a build's ledger: scenes done / failed / pending, time per stage, failures with
    reasons, and which of its scenes are locked now and by whom."""
    from paradrive.pipeline.ledger import dumps
    from paradrive.pipeline.status import build_status

    try:
        summary = build_status(build, manifests, data, storage_option)
    except (ParaDriveError, OSError) as exc:
        fail(str(exc), err=new_console(stderr=True), soft_wrap=False)
    if as_json:
        print(dumps(summary))
        return
    print_status(summary, new_console(), all_scenes=all_scenes)


def register(app: typer.Typer) -> None:
    """Add ``paradrive status`` to the command line."""
    app.command("status")(status)
