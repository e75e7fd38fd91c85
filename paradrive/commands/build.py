"""``paradrive build``: run the pipeline on scenes, with the build's ledger, a live display on a
terminal, a line per stage result, the summary and each scene's footprint."""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import typer
from rich.markup import escape
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)
from rich.table import Table

from paradrive.commands.common import DEFAULT_DATA, DEFAULT_MANIFESTS, DEFAULT_SCENE, console, fail, out, split_csv
from paradrive.errors import EXIT_INTERRUPTED, EXIT_TERMINATED, EXIT_USAGE, ConfigError, ParaDriveError, Terminated
from paradrive.pipeline.locks import DEFAULT_LOCK_TIMEOUT_S
from paradrive.redact import remember
from paradrive.storage import data_root

MB = 1e6


def build(
    scene: list[str] = typer.Option([], "--scene", help="Scene URI, e.g. 'synthetic:demo?seed=7'. Repeatable."),
    scenes: list[str] = typer.Option([], "--scenes", help="A scene list file (one URI or path a line, '#' comments), a folder of logs (*.tfrecord, a nuScenes dataroot, DriveStudio folders), or URIs. Repeatable."),
    profile: str | None = typer.Option(None, "--profile", "-p", help="Parameter profile (stages/profiles/NAME.yaml); default: the paper's."),
    stages: str | None = typer.Option(None, "--stages", help="Comma-separated stages to run (default: all)."),
    data: str = typer.Option(str(DEFAULT_DATA), "--data", help="Where scenes are written (<data>/scenes/<scene_id>): a folder (with --executor ray, one every node sees at this path) or an fsspec URL such as s3://bucket/prefix, which each worker copies scenes from and back."),
    storage_option: list[str] = typer.Option([], "--storage-option", help="fsspec option for a URL --data, KEY=VALUE (VALUE as JSON when it parses), e.g. endpoint_url=http://minio:9000. Repeatable."),
    cache: Path | None = typer.Option(None, "--cache", help="With a URL --data: where each node keeps its copy of the scenes (default: $PARADRIVE_CACHE, else ~/.cache/paradrive)."),
    drop_cache: bool = typer.Option(False, "--drop-cache", help="With a URL --data: delete a scene's local copy once each stage is uploaded (less disk, more downloads)."),
    manifests: Path = typer.Option(DEFAULT_MANIFESTS, "--manifests", help="Where builds (pair manifests) are written."),
    build_name: str = typer.Option("default", "--build", help="Build name: manifests and the status ledger go to <manifests>/<build>."),
    executor: str = typer.Option("local", "--executor", help="local (this process) or ray (each scene stage a Ray task)."),
    address: str | None = typer.Option(None, "--address", help="Ray cluster address, e.g. 'auto' or 'head:6379' (default: start a local Ray)."),
    gpu_policy: str = typer.Option("auto", "--gpu-policy", help="ray: auto (GPU stages run on CPU when the cluster has no GPU, with a warning), require (refuse), cpu (never ask for GPUs)."),
    max_in_flight: int | None = typer.Option(None, "--max-in-flight", min=1, help="ray: at most this many tasks submitted at once (default: twice the cluster's CPUs + GPUs)."),
    max_retries: int = typer.Option(2, "--max-retries", min=0, help="ray: times a task whose worker died is submitted again (each try counts in the ledger)."),
    set_: list[str] = typer.Option([], "--set", help="Override a parameter: stage.param=value. Repeatable."),
    force: bool = typer.Option(False, "--force", help="Redo stages even when their outputs are up to date."),
    verify_outputs: bool = typer.Option(False, "--verify-outputs", help="Also re-hash every stage's outputs (not only their sizes; the clips' are always re-hashed) and redo a stage whose files changed."),
    retry_failed: bool = typer.Option(False, "--retry-failed", help="Run again only what the ledger records as failed: its failed scenes, or a failed publish (manifest) when every scene is done; the manifest still covers the whole build."),
    lock_timeout: float = typer.Option(DEFAULT_LOCK_TIMEOUT_S, "--lock-timeout", min=0, help="Seconds to wait for a scene another build holds locked; after that the scene is left for this run (reported failed, naming that build)."),
    split: str | None = typer.Option(None, "--split", help="Build exactly the scenes of this split (splits/NAME.txt, or a split file's path) found among --scenes; every line must match one log."),
    exclude_split: list[str] = typer.Option([], "--exclude-split", help="Leave out the scenes of this split (repeatable; default: manifest.exclude_splits, i.e. paper-eval; 'none' keeps every scene). Training builds only."),
    kind: str | None = typer.Option(None, "--kind", help="training (pairs) or inference (source = the recording, condition = the final checkpoint's shifted render); default: manifest.kind."),
) -> None:
    """Run the pipeline on one or many scenes; stages that are up to date are skipped.

    A scene that fails never stops the others: it is recorded in the build's ledger with its
    reason (see 'paradrive status BUILD'). Exit code 0: all done and published; 3: partial (some
    scenes failed, the rest landed); 1: nothing landed (no scene, or the publish failed); 2: usage
    error.
    """
    ray_options = {"address": address, "gpu_policy": gpu_policy, "max_in_flight": max_in_flight,
                   "max_retries": max_retries}
    try:
        run = _prepare(scene, scenes, profile, stages, set_, kind, manifests, build_name, retry_failed,
                       split, exclude_split, executor, ray_options if executor == "ray" else {})
        root = data_root(data, storage_option, cache, drop_cache)
        remember(root.storage_options)
    except (ConfigError, ParaDriveError, ValueError) as exc:
        fail(str(exc))
    _run(run, root, force=force, lock_timeout=lock_timeout, verify_outputs=verify_outputs)


@dataclass
class _Run:
    """What a build runs, as its options resolve before any work."""

    config: Any
    stage_list: list[str] | None
    uris: list[str]
    build_uris: list[str] | None   # --retry-failed: the manifest's scenes, beyond those retried
    selection: Any
    ledger: Any
    runner: Any
    manifests: Path
    build_name: str
    retry_failed: bool


def _prepare(scene: list[str], scenes: list[str], profile: str | None, stages: str | None,
             set_: list[str], kind: str | None, manifests: Path, build_name: str, retry_failed: bool,
             split: str | None, exclude_split: list[str], executor: str, options: dict) -> _Run:
    """The build's configuration, scenes, ledger and executor: every usage error (a parameter, a
    stage, a scene that is not there, a split) before the ledger opens or a lock is taken."""
    from paradrive.pipeline import StageRegistry, parse_overrides
    from paradrive.pipeline.executors import make_executor
    from paradrive.pipeline.scenes import check_present

    overrides = parse_overrides(set_)
    if kind:
        overrides.setdefault("manifest", {})["kind"] = kind
    config = StageRegistry().resolve(profile, overrides)
    stage_list = split_csv(stages)
    config.check(stage_list)  # unknown stages and values no stage can take fail before any work
    build_uris: list[str] | None = None
    if retry_failed:
        if scene or scenes:
            fail("--retry-failed takes the scenes from the ledger; leave out --scene/--scenes")
        ledger = _open_ledger(manifests, build_name)
        uris, build_uris = ledger.failed_scene_uris(), ledger.scene_uris()
        unpublished = ledger.unfinished_build_stages()
        if not uris and not unpublished:
            out.print(f"nothing to retry: the ledger of build '{build_name}' records no failed "
                      f"scene and no failed publish", markup=False)
            raise typer.Exit(0)
        if not uris:   # every scene is done, the publish is not: run only what failed
            uris, stage_list = build_uris, stage_list or unpublished
            out.print(f"retrying {', '.join(unpublished)} of build '{build_name}' over its "
                      f"{len(build_uris)} scene(s)", markup=False)
    else:
        uris = collect_scene_uris(scene, scenes) or ([] if scenes else [DEFAULT_SCENE])
        if not uris:
            fail(f"--scenes {' '.join(scenes)}: no scenes found")
    check_present(uris, ingest=config.params.get("ingest"))   # inputs that are not there: one line, before the ledger or a lock
    selection = select_scenes(config, uris, split, exclude_split)
    if not retry_failed:
        ledger = _open_ledger(manifests, build_name)
    return _Run(config, stage_list, selection.uris, build_uris, selection, ledger,
                make_executor(executor, **options), manifests, build_name, retry_failed)


def _run(run: _Run, root, *, force: bool, lock_timeout: float, verify_outputs: bool) -> None:
    """Run the build; Ctrl-C and SIGTERM end it with the line saying what stopped and how to go
    on. Exits with the build's code."""
    active: dict[tuple[str, str], None] = {}
    try:
        with _terminate_as_interrupt():
            report = _run_with_progress(run.config, run.uris, root, run.stage_list, run.runner,
                                        run.manifests, run.build_name, force, run.ledger,
                                        build_uris=run.build_uris, replace=not run.retry_failed,
                                        lock_timeout=lock_timeout, selection=run.selection,
                                        active=active, verify_outputs=verify_outputs)
    except (ConfigError, ParaDriveError) as exc:
        run.ledger.end_run(EXIT_USAGE)
        fail(str(exc))
    except KeyboardInterrupt as exc:   # Ctrl-C, or SIGTERM (Terminated)
        code = EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED
        run.ledger.end_run(code)
        console.print(interrupted_message(active, "terminated (SIGTERM)" if code == EXIT_TERMINATED
                                          else "interrupted"),
                      markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(code) from None
    run.ledger.end_run(report.exit_code)
    _print_report(report, run.ledger)
    _print_footprint(root, report)
    raise typer.Exit(report.exit_code)


def collect_scene_uris(scene: list[str], scenes: list[str]) -> list[str]:
    """URIs from --scene (one URI each) and --scenes (a list file, a folder of logs, or URIs),
    each log once and each with a scene id of its own (:mod:`paradrive.pipeline.scenes`)."""
    from paradrive.pipeline.scenes import scene_uris

    return scene_uris(scene, scenes)


def interrupted_message(active: dict[tuple[str, str], None], how: str = "interrupted") -> str:
    """What Ctrl-C (or SIGTERM) stopped, and how to go on: ``interrupted: stopped fit of
    scene-a; ...``."""
    stopped = ", ".join(f"{stage} of {scene}" for scene, stage in active) or "the build between stages"
    return (f"{how}: stopped {stopped}; finished stages are kept: run the same command "
            f"again to resume (a fit goes on from its last saved state)")


@contextlib.contextmanager
def _terminate_as_interrupt() -> Iterator[None]:
    """While the build runs, SIGTERM unwinds it as Ctrl-C does (:class:`Terminated`); the
    handler before is put back after. Off the main thread nothing changes (signals are the
    main thread's)."""
    def terminated(signum, frame):
        raise Terminated()

    try:
        before = signal.signal(signal.SIGTERM, terminated)
    except ValueError:   # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, before)


def footprint_table(footprints: dict[str, dict[str, int]], max_rows: int = 20) -> Table:
    """Scenes by top folder in MB, with a total row (the largest ``max_rows`` scenes shown)."""
    from paradrive.contracts.layout import SCENE_FOLDERS
    from paradrive.pipeline.budget import OTHER

    columns = [*SCENE_FOLDERS, OTHER]
    table = Table(title="footprint (MB)", title_justify="left")
    table.add_column("scene")
    for name in [*columns, "total"]:
        table.add_column(name, justify="right")
    ranked = sorted(footprints.items(), key=lambda kv: -sum(kv[1].values()))
    for sid, sizes in ranked[:max_rows]:
        table.add_row(sid, *[f"{sizes[c] / MB:.1f}" for c in columns], f"{sum(sizes.values()) / MB:.1f}")
    if len(footprints) > 1:
        totals = {c: sum(f[c] for f in footprints.values()) for c in columns}
        table.add_row(f"all {len(footprints)} scenes", *[f"{totals[c] / MB:.1f}" for c in columns],
                      f"{sum(totals.values()) / MB:.1f}", style="bold")
    return table


def _print_footprint(root, report) -> None:
    """Each scene's bytes by folder (images, lidar, gs, renders, clips, ...) after the build."""
    from paradrive.pipeline.budget import scene_footprint

    scene_ids = list(report.scenes())
    if not scene_ids:   # a run of the build stages alone (a retried publish)
        return
    try:
        out.print(footprint_table({sid: scene_footprint(root, sid) for sid in scene_ids}))
    except OSError as exc:  # a URL data root that cannot be listed now: the build itself is done
        console.print(f"footprint not shown: {exc}", markup=False)


def select_scenes(config, uris: list[str], split: str | None, exclude_split: list[str]):
    """The build's scenes after --split and the exclusion; prints what was left out."""
    from paradrive import splits
    from paradrive.pipeline.build import default_selection

    if split:
        uris = splits.select(uris, split)
        out.print(f"split {split}: {len(uris)} scene(s)", markup=False)
    # an explicit --split is the selection: the default exclusion would empty paper-eval
    names = exclude_split or (["none"] if split else None)
    selection = default_selection(config, uris, names)
    for e in selection.excluded:
        out.print(f"excluded {e['scene_id']} (split {e['split']}: {e['line']})", markup=False)
    if selection.excluded:
        out.print(f"{len(selection.excluded)} scene(s) excluded by split(s) "
                  f"{', '.join(s.name for s in selection.splits)}", markup=False)
    if not selection.uris:
        raise ConfigError("every scene given is excluded by a split; nothing to build (pass "
                          "--exclude-split none to build them)")
    return selection


def _open_ledger(manifests: Path, build_name: str):
    from paradrive.contracts.layout import checked_build_name
    from paradrive.pipeline.ledger import Ledger

    return Ledger.for_build(manifests, checked_build_name(build_name))


def _run_with_progress(config, uris, data, stage_list, runner, manifests, build_name, force, ledger,
                       *, build_uris=None, replace=True, lock_timeout=DEFAULT_LOCK_TIMEOUT_S,
                       selection=None, active=None, verify_outputs=False):
    """Run the build with the ledger updated and, on a terminal, a live display: a bar over
    scenes (done / failed, ETA) with the per-stage counts, and a bar per running stage with its
    figures (the fit's loss, PSNR, Gaussians, it/s, ETA; render's frames; clip's streams)."""
    from paradrive.pipeline.build import run_build, split_stages
    from paradrive.pipeline.progress import StageCounts
    from paradrive.uri import parse_uri

    scene_stages, build_stages = split_stages(config, stage_list)
    last_stage = scene_stages[-1] if scene_stages else None
    progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                        TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(),
                        TextColumn("{task.fields[figures]}"),
                        console=console, transient=False, disable=not console.is_terminal)
    counts = {"done": 0, "failed": 0}
    stages = StageCounts(scene_stages, len(uris))
    running: dict[tuple[str, str], TaskID] = {}
    ids = {uri: parse_uri(uri).scene_id for uri in uris}
    active = {} if active is None else active   # (scene id, stage) running now, for Ctrl-C

    def describe(activity: str) -> str:
        failed = f", [red]{counts['failed']} failed[/]" if counts["failed"] else ""
        return f"{counts['done']} done{failed} | {activity}"

    def on_start(scene: str, stage: str) -> None:
        active[(ids.get(scene, scene), stage)] = None
        stages.start(scene, stage)
        progress.update(task, description=describe(f"{stage} {ids.get(scene, scene)}"),
                        figures=stages.line())
        ledger.start(scene, stage)

    def on_progress(snap) -> None:
        key = (snap.scene_id, snap.stage)
        if key not in running:
            running[key] = progress.add_task(f"  {snap.stage} {snap.scene_id}", total=snap.total,
                                             figures="")
        progress.update(running[key], completed=snap.done, total=snap.total, figures=snap.figures())

    def on_result(result) -> None:
        active.pop((result.scene_id, result.stage), None)
        ledger.record(result)
        stages.result(result)
        if (result.scene_id, result.stage) in running:
            progress.remove_task(running.pop((result.scene_id, result.stage)))
        is_scene = not result.scene_id.startswith("build:")
        if is_scene and result.status == "failed":
            counts["failed"] += 1
            progress.advance(task)
        elif is_scene and result.stage == last_stage and result.status in ("done", "skipped"):
            counts["done"] += 1
            progress.advance(task)
        progress.update(task, description=describe(f"{result.stage} {result.scene_id} {result.status}"),
                        figures=stages.line())
        style = {"done": "green", "skipped": "dim", "failed": "red", "blocked": "yellow"}[result.status]
        console.print(f"[{style}]{result.status:>7}[/] {result.stage:<8} {escape(result.scene_id)}"
                      + (f" — {escape(result.error)}" if result.error else f" ({result.seconds:.1f} s)"),
                      soft_wrap=True)   # a line per result, whatever the width

    ledger.register(uris, scene_stages, build_stages, replace=replace)
    ledger.begin_run(getattr(runner, "name", ""), len(uris))
    ledger.set_data_root(str(data))
    with progress:
        task = progress.add_task(describe("starting"), total=len(uris) if scene_stages else None,
                                 figures=stages.line())
        return run_build(config, uris, data, stages=stage_list, executor=runner,
                         manifests_dir=manifests, build=build_name, force=force,
                         build_scene_uris=build_uris, selection=selection,
                         on_start=on_start, on_result=on_result, lock_timeout=lock_timeout,
                         on_progress=on_progress if console.is_terminal else None,
                         verify_outputs=verify_outputs)


def _print_report(report, ledger=None, max_rows: int = 20) -> None:
    """Summary: every scene when there are few, else the failures only; the build stages."""
    scenes = report.scenes()
    done = sum(1 for s in scenes.values() if s == "done")
    reasons: dict[str, str] = {}
    for r in report.failures():
        reasons.setdefault(r.scene_id, f"{r.stage}: {r.error}")
    shown = scenes if len(scenes) <= max_rows else {k: v for k, v in scenes.items() if v != "done"}
    table = Table(title="build summary", show_lines=False)
    table.add_column("scene")
    table.add_column("status")
    table.add_column("reason", overflow="fold")
    for sid, state in list(shown.items())[:200]:
        table.add_row(escape(sid), "[green]done" if state == "done" else "[red]failed", escape(reasons.get(sid, "")))
    for r in report.results:
        if r.scene_id.startswith("build:"):
            table.add_row(escape(r.scene_id), r.status, escape(r.error))
    out.print(table)
    more = f" (status of all: paradrive status {ledger.build} --manifests {ledger.path.parent.parent})" \
        if ledger is not None else ""
    counted = (f"{done} of {len(scenes)} scenes done" if scenes or not report.results
               else f"build {report.results[-1].scene_id[len('build:'):]}: "
                    + ", ".join(f"{r.stage} {r.status}" for r in report.results))
    out.print(counted
              + ("" if report.exit_code == 0 else f"; exit code {report.exit_code} "
                 f"({_outcome(report)})") + more, markup=False)


def _outcome(report) -> str:
    """The words for a build's non-zero exit code in its last line."""
    if report.exit_code == 3:
        return "partial build"
    failed = [r.stage for r in report.failures() if r.scene_id.startswith("build:")]
    if failed and any(state == "done" for state in report.scenes().values()):
        return (f"{', '.join(failed)} failed: nothing of this run was published; "
                f"retry it with --retry-failed")
    return "no scene built"


def register(app: typer.Typer) -> None:
    """Add ``paradrive build`` to the command line."""
    app.command()(build)
