"""``paradrive inspect BUILD``: counts, quality, checksum verification and pictures of a
published build (:mod:`paradrive.inspection` gathers and checks them)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from paradrive.commands.common import fail, new_console
from paradrive.errors import ParaDriveError

if TYPE_CHECKING:  # the build's readers are imported when the command runs
    from paradrive.contracts.records import IndexRecord


def print_summary(summary: dict, console: Console) -> None:
    """The summary of :func:`paradrive.inspection.summarize` as tables, on ``console``."""
    console.print(f"[bold]{escape(summary['build'])}[/]: {summary['rows']} pairs in {summary['shards']} "
                  f"shards (fingerprint {summary['config_fingerprint']}, paradrive "
                  f"{(summary.get('software') or {}).get('paradrive', '?')}, "
                  f"{escape(' and '.join(summary.get('transform') or ['lateral']))} sources)")
    titles = {"dataset": "dataset", "scene": "scene", "camera": "camera", "clip": "clip",
              "offset": "offset", "checkpoint": "condition checkpoint"}
    grid = Table.grid(padding=(0, 2))
    small = []
    for key, title in titles.items():
        t = Table(title=f"pairs by {title}", title_justify="left")
        t.add_column(title)
        t.add_column("pairs", justify="right")
        for k, v in summary["counts"][key].items():
            t.add_row(escape(str(k)), str(v))
        small.append(t)
    grid.add_row(*small[:3])
    grid.add_row(*small[3:])
    console.print(grid)
    its = list(summary["quality"]["by_checkpoint"])
    q = Table(title="quality: condition vs target (mean over pairs), fit on training views",
              title_justify="left")
    q.add_column("scene")
    q.add_column("fit PSNR", justify="right")
    q.add_column("held-out PSNR", justify="right")
    for it in its:
        q.add_column(f"cond {it} PSNR / SSIM", justify="right")

    def fmt(v, digits):
        return "-" if v is None else f"{v:.{digits}f}"

    for sid, s in summary["quality"]["scenes"].items():
        q.add_row(escape(sid), fmt(s["fit_train_psnr"], 2), fmt(s.get("heldout_psnr"), 2),
                  *[f"{fmt(s['condition'].get(it, {}).get('psnr'), 2)} / "
                    f"{fmt(s['condition'].get(it, {}).get('ssim'), 3)}" for it in its])
    allq = summary["quality"]["by_checkpoint"]
    q.add_row("[bold]all", "", "", *[f"{fmt(allq[it]['psnr'], 2)} / {fmt(allq[it]['ssim'], 3)}"
                                  for it in its])
    console.print(q)
    for s in summary["skipped_scenes"]:
        console.print(f"[yellow]skipped scene[/] {escape(s['scene_id'])}: {escape(s['reason'])}")
    if summary.get("heldout_filter"):
        f = summary["heldout_filter"]
        console.print(f"held-out PSNR filter: at least {f['min_psnr']:g} dB, "
                      f"{len(f['dropped'])} scene(s) left out", markup=False)
    splits = ", ".join(f"{s['name']} (sha256 {s['sha256'][:12]}…, {s['scenes']} scenes)"
                       for s in summary["exclude_splits"]) or "none"
    console.print(f"{summary['kind']} build; excluded splits: {splits}", markup=False)
    for s in summary["excluded_scenes"]:
        console.print("[yellow]excluded scene[/] "
                      + escape(f"{s['scene_id']} (split {s['split']}: {s['line']})"))


def verify_and_report(build: Path, err: Console, jobs: int | None = None, index: IndexRecord | None = None) -> dict:
    """Verify ``build``, printing each problem and the verdict on ``err``."""
    from paradrive.inspection import verify_build

    result = verify_build(build, jobs, index)
    for p in result["problems"]:
        err.print(f"[red]{escape(p)}[/]", soft_wrap=True)
    if result["ok"]:
        err.print(f"[green]verified[/] {result['checked_files']} files")
    else:
        err.print(f"[bold red]{len(result['problems'])} of {result['checked_files']} files "
                  f"missing, corrupt or unsafe[/]")
    return result


def inspect_cmd(
    build: Path = typer.Argument(..., help="The build folder (<manifests>/<build>, holding index.json)."),
    verify: bool = typer.Option(False, "--verify", help="Re-hash every shard and referenced video; exit 1 naming each missing, corrupt or unsafe (leading out of the build) one."),
    as_json: bool = typer.Option(False, "--json", help="Print a machine-readable summary instead of tables."),
    sheet: Path | None = typer.Option(None, "--sheet", help="Write a contact sheet PNG here (and next to it <name>_trajectories.png, the camera paths from above, and <name>_rig.png, the rig and its shifted cameras in 3D)."),
    pairs: int = typer.Option(3, "--pairs", help="Pairs on the contact sheet."),
    data: Path | None = typer.Option(None, "--data", help="Data folder to find the scene's LiDAR in (default: the scene folders index.json records)."),
    jobs: int | None = typer.Option(None, "--jobs", min=1, help="With --verify: files hashed at once (default: the CPUs, at most 8)."),
) -> None:
    """Counts, quality, checksum verification and pictures of a published build."""
    from paradrive.inspection import summarize
    from paradrive.pairs import read_index

    out, err = new_console(), new_console(stderr=True)
    try:
        index = read_index(build)   # one version for everything below, however long it takes
        result = verify_and_report(build, err, jobs, index) if verify else None
        code = 0 if result is None or result["ok"] else 1
        try:
            summary = summarize(build, index)
        except ParaDriveError:
            if code:  # a shard that cannot be read: already reported as corrupt
                raise typer.Exit(code) from None
            raise
    except ParaDriveError as exc:
        fail(str(exc), err=err, soft_wrap=False)
    if result is not None:
        summary["verify"] = result
    if sheet is not None:
        code = _pictures(build, sheet, pairs, data, index, summary, err) or code
    if as_json:
        typer.echo(json.dumps(summary, indent=2))
    else:
        from paradrive.latents import latents_summary  # torch: not at every command's start

        print_summary(summary, out)
        out.print(latents_summary(build), markup=False)
        for key in ("sheet", "trajectories", "rig"):
            if key in summary:
                out.print(f"wrote {summary[key]}", markup=False)
    raise typer.Exit(code)


def _pictures(build: Path, sheet: Path, pairs: int, data: Path | None, index: IndexRecord,
              summary: dict, err: Console) -> int:
    """The contact sheet and, beside it, the trajectories and the rig (their paths go into
    ``summary``); 1 when one could not be made (its reason printed), else 0."""
    from paradrive.inspection import contact_sheet, rig_picture, trajectories_picture

    try:
        summary["sheet"] = str(contact_sheet(build, sheet, pairs=pairs, index=index))
        traj = sheet.with_name(f"{sheet.stem}_trajectories.png")
        summary["trajectories"] = str(trajectories_picture(build, traj, data_dir=data))
        rig = sheet.with_name(f"{sheet.stem}_rig.png")
        summary["rig"] = str(rig_picture(build, rig, data_dir=data))
    except ParaDriveError as exc:
        err.print(f"[bold red]error:[/] {escape(str(exc))}")
        return 1
    return 0


def register(app: typer.Typer) -> None:
    """Add ``paradrive inspect`` to the command line."""
    app.command("inspect")(inspect_cmd)
