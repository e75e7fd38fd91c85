"""The ``paradrive`` command line."""

from __future__ import annotations

import contextlib
import importlib
import logging
import signal
import sys
from collections.abc import Iterator
from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeElapsedColumn,
                           TimeRemainingColumn)
from rich.table import Table

from paradrive import __version__
from paradrive.errors import (EXIT_FAILED, EXIT_INTERRUPTED, EXIT_TERMINATED, EXIT_USAGE, ConfigError,
                              ParaDriveError, Terminated, missing_extra)
from paradrive.pipeline.locks import DEFAULT_LOCK_TIMEOUT_S
from paradrive.redact import remember
from paradrive.storage import data_root

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Build parallel-trajectory video pairs from single-pass driving logs.")
console = Console(stderr=True)
out = Console()

DEFAULT_DATA = Path("data")
DEFAULT_MANIFESTS = Path("manifests")
DEFAULT_SCENE = "synthetic:demo?seed=7"


def fail(message: str, code: int = EXIT_USAGE) -> None:
    console.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True)  # one line, whatever the width
    raise typer.Exit(code)


def version_callback(value: bool) -> None:
    if value:
        out.print(f"paradrive {__version__}")
        raise typer.Exit()


@app.callback()
def main_callback(version: bool = typer.Option(False, "--version", callback=version_callback,
                                               is_eager=True, help="Print the version.")) -> None:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")


def _split_csv(value: str | None) -> list[str] | None:
    if not value:
        return None
    return [v.strip() for v in value.split(",") if v.strip()]


def collect_scene_uris(scene: list[str], scenes: list[str]) -> list[str]:
    """URIs from --scene (one URI each) and --scenes (a list file, a folder of logs, or URIs),
    each log once and each with a scene id of its own (:mod:`paradrive.pipeline.scenes`)."""
    from paradrive.pipeline.scenes import scene_uris

    return scene_uris(scene, scenes)


@app.command()
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
    retry_failed: bool = typer.Option(False, "--retry-failed", help="Run again only the scenes the ledger records as failed; the manifest still covers the whole build."),
    lock_timeout: float = typer.Option(DEFAULT_LOCK_TIMEOUT_S, "--lock-timeout", min=0, help="Seconds to wait for a scene another build holds locked; after that the scene is left for this run (reported failed, naming that build)."),
    split: str | None = typer.Option(None, "--split", help="Build exactly the scenes of this split (splits/NAME.txt, or a split file's path) found among --scenes; every line must match one log."),
    exclude_split: list[str] = typer.Option([], "--exclude-split", help="Leave out the scenes of this split (repeatable; default: manifest.exclude_splits, i.e. paper-eval; 'none' keeps every scene). Training builds only."),
    kind: str | None = typer.Option(None, "--kind", help="training (pairs) or inference (source = the recording, condition = the final checkpoint's shifted render); default: manifest.kind."),
) -> None:
    """Run the pipeline on one or many scenes; stages that are up to date are skipped.

    A scene that fails never stops the others: it is recorded in the build's ledger with its
    reason (see 'paradrive status BUILD'). Exit code 0: all done; 3: partial (some scenes failed,
    the rest landed); 1: nothing succeeded; 2: usage error.
    """
    from paradrive.pipeline import StageRegistry, parse_overrides
    from paradrive.pipeline.executors import make_executor
    from paradrive.pipeline.scenes import check_present

    build_uris: list[str] | None = None
    try:
        overrides = parse_overrides(set_)
        if kind:
            overrides.setdefault("manifest", {})["kind"] = kind
        config = StageRegistry().resolve(profile, overrides)
        stage_list = _split_csv(stages)
        config.check(stage_list)  # unknown stages and values no stage can take fail before any work
        if retry_failed:
            if scene or scenes:
                fail("--retry-failed takes the scenes from the ledger; leave out --scene/--scenes")
            ledger = _open_ledger(manifests, build_name)
            uris = ledger.failed_scene_uris()
            if not uris:
                out.print(f"nothing to retry: the ledger of build '{build_name}' records no failed scene",
                          markup=False)
                raise typer.Exit(0)
            build_uris = ledger.scene_uris()
        else:
            uris = collect_scene_uris(scene, scenes) or ([] if scenes else [DEFAULT_SCENE])
            if not uris:
                fail(f"--scenes {' '.join(scenes)}: no scenes found")
        check_present(uris)   # inputs that are not there: one line, before the ledger or a lock
        selection = select_scenes(config, uris, split, exclude_split)
        uris = selection.uris
        if not retry_failed:
            ledger = _open_ledger(manifests, build_name)
        options = {"address": address, "gpu_policy": gpu_policy, "max_in_flight": max_in_flight,
                   "max_retries": max_retries} if executor == "ray" else {}
        runner = make_executor(executor, **options)
        root = data_root(data, storage_option, cache, drop_cache)
        remember(root.storage_options)
    except (ConfigError, ParaDriveError, ValueError) as exc:
        fail(str(exc))

    active: dict[tuple[str, str], None] = {}
    try:
        with _terminate_as_interrupt():
            report = _run_with_progress(config, uris, root, stage_list, runner, manifests,
                                        build_name, force, ledger, build_uris=build_uris,
                                        replace=not retry_failed, lock_timeout=lock_timeout,
                                        selection=selection, active=active,
                                        verify_outputs=verify_outputs)
    except (ConfigError, ParaDriveError) as exc:
        ledger.end_run(EXIT_USAGE)
        fail(str(exc))
    except KeyboardInterrupt as exc:   # Ctrl-C, or SIGTERM (Terminated)
        code = EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED
        ledger.end_run(code)
        console.print(interrupted_message(active, "terminated (SIGTERM)" if code == EXIT_TERMINATED
                                          else "interrupted"),
                      markup=False, highlight=False, soft_wrap=True)
        raise typer.Exit(code) from None
    ledger.end_run(report.exit_code)
    _print_report(report, ledger)
    _print_footprint(root, report)
    raise typer.Exit(report.exit_code)


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


def _print_footprint(root, report) -> None:
    """Each scene's bytes by folder (images, lidar, gs, renders, clips, ...) after the build."""
    from paradrive.pipeline.budget import footprint_table, scene_footprint

    scene_ids = list(report.scenes())
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
    out.print(f"{done} of {len(scenes)} scenes done"
              + ("" if report.exit_code == 0 else f"; exit code {report.exit_code} "
                 f"({'partial build' if report.exit_code == 3 else 'no scene built'})") + more, markup=False)


@app.command("stages")
def stages_cmd(
    profile: str | None = typer.Option(None, "--profile", "-p", help="Show values under this profile."),
    set_: list[str] = typer.Option([], "--set", help="Override: stage.param=value."),
    stage: str | None = typer.Argument(None, help="Only this stage."),
) -> None:
    """List the stages, their parameters, values and where each value comes from."""
    from paradrive.pipeline import StageRegistry, parse_overrides

    try:
        registry = StageRegistry()
        config = registry.resolve(profile, parse_overrides(set_))
        names = registry.order([stage] if stage else None)
    except ConfigError as exc:
        fail(str(exc))
    for name in names:
        spec = registry.specs[name]
        res = spec.resources
        table = Table(title=f"{name} [dim]({Path(spec.file).name}; needs: {', '.join(spec.needs) or '-'}; "
                            f"{spec.scope}; cpu {res.cpu:g}, gpu {res.gpu:g}, {res.memory_gb:g} GB)[/]",
                      title_justify="left")
        table.add_column("parameter")
        table.add_column("value")
        table.add_column("allowed", overflow="fold")
        table.add_column("from")
        table.add_column("why / source", overflow="fold")
        for key, param in spec.params.items():
            origin = config.origins[name][key]
            value = config.params[name][key]
            allowed = param.allowed() + (", or null" if param.default is None or param.nullable else "")
            table.add_row(key, escape(repr(value)), escape(allowed),
                          origin if origin == "default" else f"[yellow]{escape(origin)}", escape(param.doc))
        out.print(table)
    out.print(f"profiles: paper (defaults), {', '.join(registry.profiles())}", markup=False)


# Commands that live next to the code they drive. Each module exposes ``register(app)``.
@app.command("export")
def export_cmd(
    fmt: str = typer.Argument(..., help="waymo, nuscenes, drivestudio or video (the front camera as a plain MP4)"),
    out: Path = typer.Argument(..., help="Folder to write the log into."),
    scene: str = typer.Option("synthetic:demo?seed=7", "--scene", help="A synthetic scene URI."),
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

    if before is None:
        shutil.rmtree(out, ignore_errors=True)
        return
    for path in sorted(set(out.rglob("*")) - before, key=lambda p: len(p.parts), reverse=True):
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)


@app.command("view")
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


COMMAND_MODULES = [
    ("paradrive.inspection", "inspect"),
    ("paradrive.evaluation", "eval"),
    ("paradrive.pipeline.status", "status"),
    ("paradrive.pipeline.budget", "plan"),
    ("paradrive.train.cli", "train"),
    ("paradrive.wan.cli", "encode"),   # and convert, generate
]


def _register_commands() -> None:
    for module_name, command in COMMAND_MODULES:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if not (exc.name and module_name.startswith(exc.name)):
                raise
            _register_missing(command, module_name)
            continue
        module.register(app)


def _register_missing(command: str, module_name: str) -> None:
    @app.command(command, context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
                 help=f"(not available in this installation: {module_name} is missing)")
    def _missing() -> None:
        fail(f"'paradrive {command}' is not available: {module_name} is not installed")


_register_commands()


def main() -> None:
    try:
        app()
    except ConfigError as exc:
        console.print(f"[bold red]error:[/] {escape(str(exc))}", soft_wrap=True)
        sys.exit(EXIT_USAGE)
    except ModuleNotFoundError as exc:
        missing = missing_extra(exc)
        if missing is None:
            raise
        console.print(f"[bold red]error:[/] {escape(str(missing))}", soft_wrap=True)
        sys.exit(EXIT_USAGE)


if __name__ == "__main__":
    main()
