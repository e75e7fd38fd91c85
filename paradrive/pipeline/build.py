"""A build: scene stages for many scenes through an executor, then the build-scoped stages.

Exit codes of a build (also the CLI's; the table in docs/operations.md): 0 every scene finished
every asked stage and the publish landed; 3 partial (some scenes failed, the others landed); 1
nothing landed (no scene finished, or the publish failed); 2 a usage or configuration error,
found before any stage ran; 130 interrupted (Ctrl-C), 143 terminated (SIGTERM).
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import resource
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Callable, Iterator

from paradrive import splits
from paradrive.errors import (EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, EXIT_PARTIAL, EXIT_USAGE,
                              ConfigError, ParaDriveError, StageNotImplemented)
from paradrive.io import stop_point
from paradrive.pipeline.executors import Executor, LocalExecutor, RunOptions, SceneTask
from paradrive.pipeline.locks import DEFAULT_LOCK_TIMEOUT_S, HeldLock, LockOptions, scene_lock
from paradrive.pipeline.progress import ProgressSink
from paradrive.pipeline.scenes import SceneInput, check_present, distinct_scenes
from paradrive.pipeline.runner import (
    MARKER_DIR, StageResult, damaged_outputs, expand_outputs, fingerprint,
    load_entry, local_sha256, local_size, marker_path, peak_rss_mb, read_marker, scene_dir_for,
    stage_fingerprint,
    summary_of,
    typed_params, written_outputs,
)
from paradrive.pipeline.ledger import LEDGER_FILE
from paradrive.contracts.specs import ResolvedConfig, StageSpec
from paradrive.splits import Selection
from paradrive.contracts.base import BuildContext
from paradrive.contracts.layout import BuildLayout
from paradrive.contracts.records import StageMarker
from paradrive.io import no_room_message
from paradrive.storage import DataRoot, file_stats, matches
from paradrive.uri import parse_uri

NOT_OWNED = (f"{LEDGER_FILE}*", "logs")  # in a build folder, but no build stage's output


@dataclass
class BuildReport:
    results: list[StageResult] = field(default_factory=list)
    excluded: list[dict] = field(default_factory=list)   # scenes a split left out of the build

    def scenes(self) -> dict[str, str]:
        """scene_id -> 'done' | 'failed' (a scene fails if any of its stages failed)."""
        state: dict[str, str] = {}
        for r in self.results:
            if r.scene_id.startswith("build:"):
                continue
            if r.status in ("failed", "blocked"):
                state[r.scene_id] = "failed"
            else:
                state.setdefault(r.scene_id, "done")
        return state

    def failures(self) -> list[StageResult]:
        return [r for r in self.results if r.status == "failed"]

    @property
    def exit_code(self) -> int:
        """0 nothing failed; 3 partial: some scenes failed and the others landed; 1 nothing
        landed: no scene finished its stages, or the build's publish (a build stage) failed,
        so this run's scenes are in no published version. A build stage after a publish that
        landed (encode after manifest) failing is partial. The table is docs/operations.md's."""
        if not self.failures():
            return EXIT_OK
        build_results = [r for r in self.results if r.scene_id.startswith("build:")]
        if build_results:
            published = any(r.status in ("done", "skipped") for r in build_results)
            return EXIT_PARTIAL if published else EXIT_FAILED
        return EXIT_PARTIAL if "done" in self.scenes().values() else EXIT_FAILED


def default_selection(config: ResolvedConfig, uris: list[str],
                      exclude_splits: list[str] | None = None) -> Selection:
    """The scenes a build keeps: a training build leaves out ``exclude_splits`` (default: the
    manifest stage's ``exclude_splits``); an inference build keeps every scene. A URI whose own
    values no ingest could take is refused here, before any work (ConfigError)."""
    from paradrive.stages.ingest import check_uri

    for uri in dict.fromkeys(uris):
        check_uri(uri)
    manifest = config.params.get("manifest") or {}
    if manifest.get("kind") == "inference":
        return Selection(uris=list(uris))
    names = exclude_splits if exclude_splits is not None else manifest.get("exclude_splits", [])
    return splits.exclude(list(uris), list(names))


def split_stages(config: ResolvedConfig, stages: list[str] | None) -> tuple[list[str], list[str]]:
    registry = config.registry()
    ordered = config.selected(stages)
    scene_stages = [s for s in ordered if registry.specs[s].scope == "scene"]
    build_stages = [s for s in ordered if registry.specs[s].scope == "build"]
    return scene_stages, build_stages


def run_build_stage(config: ResolvedConfig, stage: str, scene_uris: list[str],
                    data_dir: str | Path | DataRoot, manifests_dir: Path, build: str, *,
                    force: bool = False, record: dict | None = None) -> StageResult:
    """Run a build-scoped stage over the scenes whose needed stages completed.

    With a URL data root, each scene's markers are read remotely and the files the stage
    ``reads`` are brought to this machine's cache first. The stage is up to date when the
    published index carries its fingerprint, its marker (``<build>/.paradrive/<stage>.json``)
    says no scene's needed stage was redone since, and every file it wrote is there with its
    size (a build published before these markers existed is published once more). ``record``
    (what the build left out and by which split files) reaches the stage as
    ``params["selection"]`` and its fingerprint. The scenes left out because they have not
    finished the stage's needs are listed in the result's ``summary["unfinished"]``.
    """
    root = DataRoot.of(data_dir)
    spec = config.registry().specs[stage]
    if _on_build(config, spec):
        return _run_on_build(config, stage, spec, root, BuildLayout.of(manifests_dir, build).root,
                             build, force)
    label = f"build:{build}"
    scenes, inputs, runs, mirrors, unfinished, stale = [], {}, {}, [], {}, {}
    for uri in scene_uris:
        sid = parse_uri(uri).scene_id
        sdir = scene_dir_for(root.local, sid)
        mirror = root.mirror(sid)
        try:
            if mirror:
                mirror.sync([f"{MARKER_DIR}/*.json"])
        except OSError as exc:  # StorageError: names the URL and the fix
            return StageResult(label, stage, "failed", error=f"build {build}: {exc}")
        found = [read_marker(sdir, need) for need in spec.needs]
        markers = [m for m in found if m is not None]
        reason = _made_otherwise(config, spec.needs, uri, sdir) if len(markers) == len(found) else None
        if reason:
            stale[sid] = reason
        elif len(markers) == len(found):
            scenes.append({"scene_id": sid, "scene_uri": uri, "scene_dir": str(sdir),
                           "scene_location": root.scene_location(sid)})
            inputs[sid] = ",".join(m.fingerprint for m in markers)
            runs[sid] = {need: m.run for need, m in zip(spec.needs, markers)}
            if mirror:
                mirrors.append(mirror)
        else:
            unfinished[sid] = [need for need, m in zip(spec.needs, found) if not m]
    result = _run_build_stage(config, stage, spec, root, scenes, inputs, runs, mirrors,
                              BuildLayout.of(manifests_dir, build).root, build, force, record)
    result.summary["unfinished"] = unfinished
    result.summary["stale"] = stale
    if not scenes and stale:
        result.error = f"build {build}: nothing to publish: {'; '.join(stale.values())}"
    return result


def _on_build(config: ResolvedConfig, spec: StageSpec) -> bool:
    """A build stage that works on what another build stage published (encode after manifest),
    not on the scenes: all its needs are build stages."""
    specs = config.registry().specs
    return bool(spec.needs) and all(specs[need].scope == "build" for need in spec.needs)


def _run_on_build(config: ResolvedConfig, stage: str, spec: StageSpec, root: DataRoot,
                  build_dir: Path, build: str, force: bool) -> StageResult:
    """Run a build stage whose needs are build stages, on the build folder alone.

    Its inputs are the needed stages' markers in the build folder and the published index (the
    sha256 of its shards), so a republished build with other rows runs it again. It is up to
    date when its own marker carries this fingerprint and every file it wrote is there."""
    label, t0 = f"build:{build}", time.time()
    markers = {need: read_marker(build_dir, need) for need in spec.needs}
    missing = [need for need, marker in markers.items() if marker is None]
    if missing:
        return StageResult(label, stage, "failed", error=(
            f"build {build}: {stage} needs {', '.join(missing)}, which has not published "
            f"{build_dir}; run the build with {', '.join(missing)} first"))
    try:
        index = json.loads(BuildLayout(build_dir).index_json.read_text())
    except (FileNotFoundError, json.JSONDecodeError) as exc:
        return StageResult(label, stage, "failed", error=f"build {build}: {stage} needs a published "
                                                         f"build, {build_dir}/index.json: {exc}")
    runs = {need: marker.fingerprint for need, marker in markers.items() if marker}
    shards = ",".join(str(s.get("sha256")) for s in index.get("shards", []))
    params = dict(config.params[stage])
    fp = fingerprint(stage, spec.fingerprinted(params), {**runs, "pairs": shards})
    marker = read_marker(build_dir, stage)
    if not force and marker is not None and marker.fingerprint == fp and _intact(marker, runs, build_dir):
        return StageResult(label, stage, "skipped", fingerprint=fp)
    log = logging.getLogger(f"paradrive.build.{build}")
    try:
        func = load_entry(spec)
        marker_path(build_dir, stage).unlink(missing_ok=True)
        before = file_stats(build_dir)
        ctx = BuildContext(stage=stage, build=build, layout=BuildLayout(build_dir), data_dir=root.local,
                           scenes=[], params=typed_params(spec, params), log=log, fingerprint=fp)
        summary = summary_of(func(ctx))
        declared = expand_outputs(spec.outputs, params)
        outputs = {rel: info for rel, info in written_outputs(build_dir, before, declared).items()
                   if matches(rel, declared)}
        StageMarker(stage=stage, build=build, fingerprint=fp, scene_runs=runs,
                    outputs=outputs).save(marker_path(build_dir, stage))
        return StageResult(label, stage, "done", seconds=time.time() - t0, fingerprint=fp, summary=summary)
    except Exception as exc:  # the stage's failure is its result; the run is still closed
        return _failed(exc, label, stage, build, time.time() - t0, log)


def _failed(exc: Exception, label: str, stage: str, build: str, seconds: float,
            log: logging.Logger) -> StageResult:
    """The result of a build stage that raised: the message of an expected failure (a
    ParaDriveError, a file system or value error; a full disk names the folder, the room there
    and the room needed), else a crash with its traceback in the log. Its seconds and peak
    memory are recorded as a finished stage's are."""
    if isinstance(exc, (ParaDriveError, OSError, ValueError)):
        error = (str(exc) if isinstance(exc, ParaDriveError)
                 else no_room_message(exc, f"build {build}: {stage}", elsewhere="pass another --manifests")
                 or f"build {build}: {stage} failed: {type(exc).__name__}: {exc}")
        log.error("%s: failed: %s", stage, error)
    else:  # a bug or an unexpected library error
        log.error("%s: crashed:\n%s", stage, traceback.format_exc())
        error = f"build {build}: {stage} crashed: {type(exc).__name__}: {exc}"
    return StageResult(label, stage, "failed", seconds=seconds, error=error, peak_rss_mb=peak_rss_mb())


def _made_otherwise(config: ResolvedConfig, needs: list[str], uri: str, sdir: Path) -> str | None:
    """Why a scene's outputs of ``needs`` (or of the stages before them) are not what this
    build's parameters make: the first stage whose marker another configuration wrote."""
    registry, todo, seen = config.registry(), list(needs), set()
    while todo:
        stage = todo.pop(0)
        if stage in seen:
            continue
        seen.add(stage)
        marker = read_marker(sdir, stage)
        made = marker.fingerprint if marker else None
        try:
            expected = stage_fingerprint(config, stage, uri, sdir)[0]
        except ConfigError as exc:
            return f"scene {sdir.name}: {exc}"
        if made != expected:
            return (f"scene {sdir.name}: its {stage} outputs were made with other parameters "
                    f"(marker fingerprint {made}, this build's {expected}), "
                    f"e.g. by another build on this data root; run this build without --stages "
                    f"to make them again")
        todo.extend(registry.specs[stage].needs)
    return None


def _run_build_stage(config, stage, spec, root, scenes, inputs, runs, mirrors, build_dir, build,
                     force, record) -> StageResult:
    label, t0 = f"build:{build}", time.time()
    if not scenes:
        return StageResult(label, stage, "failed",
                           error=f"build {build}: no scene finished {', '.join(spec.needs)}; "
                                 f"nothing to write")
    params = dict(config.params[stage])
    hashed = spec.fingerprinted(params)   # as every other stage's: one rule for what counts
    fp = fingerprint(stage, hashed if record is None else {**hashed, "selection": record}, inputs)
    index = BuildLayout(build_dir).index_json
    if not force and _published(index, fp) and _intact(read_marker(build_dir, stage), runs, build_dir):
        return StageResult(label, stage, "skipped", fingerprint=fp)
    log = logging.getLogger(f"paradrive.build.{build}")
    try:
        for mirror in mirrors:
            mirror.pull(spec.reads)  # a URL root: what the stage reads, to this machine
        func = load_entry(spec)
        marker_path(build_dir, stage).unlink(missing_ok=True)
        before = file_stats(build_dir)
        ctx = BuildContext(stage=stage, build=build, layout=BuildLayout(build_dir),
                           data_dir=root.local, scenes=scenes, params=typed_params(spec, params),
                           log=log, fingerprint=fp, selection=record)
        with _scene_locks(root, scenes, build, log, inputs, spec.needs) as held:
            summary = summary_of(func(ctx))
            for lock in held:   # a lease another build took: what was read may be mixed
                lock.check()
        # what this run wrote: the versions a publish keeps for their readers are no output of it
        outputs = {rel: info for rel, info in written_outputs(build_dir, before, []).items()
                   if not matches(rel, NOT_OWNED)}
        StageMarker(stage=stage, build=build, fingerprint=fp, scene_runs=runs,
                    outputs=outputs).save(marker_path(build_dir, stage))
        return StageResult(label, stage, "done", seconds=time.time() - t0, fingerprint=fp,
                           summary=summary)
    except Exception as exc:  # the stage's failure is its result; the run is still closed
        return _failed(exc, label, stage, build, time.time() - t0, log)
    finally:
        if root.drop_cache:
            for mirror in mirrors:
                mirror.drop()


@contextlib.contextmanager
def _scene_locks(root: DataRoot, scenes: list[dict], build: str, log: logging.Logger,
                 inputs: dict[str, str], needs: list[str]) -> Iterator[list[HeldLock]]:
    """Every scene's lock while a build stage reads its outputs, so no other build rewrites
    them meanwhile; the needed markers must still be the ones the stage was planned on."""
    _allow_open_files(len(scenes))
    held: list[HeldLock] = []
    with contextlib.ExitStack() as stack:
        for entry in sorted(scenes, key=lambda e: e["scene_id"]):  # one order: no deadlock
            sid = entry["scene_id"]
            held.append(stack.enter_context(scene_lock(root, sid, LockOptions(build), log)))
            now = [read_marker(Path(entry["scene_dir"]), need) for need in needs]
            if ",".join(str(m.fingerprint if m else None) for m in now) != inputs[sid]:
                raise ParaDriveError(f"scene {sid}: another build changed its {', '.join(needs)} "
                                     f"outputs while this build waited for them; re-run")
        yield held


def _allow_open_files(locks: int) -> None:
    """A scene lock on a folder root is an open file (``flock``), and a build stage holds every
    scene's at once: raise this process's soft limit on open files towards its hard limit when
    it is below them (1,024 by default on many systems, a paper-size build has 1,600 scenes)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = locks + 256  # and the files the stage itself opens
    if soft != resource.RLIM_INFINITY and soft < want:
        resource.setrlimit(resource.RLIMIT_NOFILE,
                           (want if hard == resource.RLIM_INFINITY else min(want, hard), hard))


def _published(index: Path, fp: str) -> bool:
    try:
        return json.loads(index.read_text()).get("config_fingerprint") == fp
    except (FileNotFoundError, json.JSONDecodeError):
        return False


def _intact(marker: StageMarker | None, runs: dict, build_dir: Path) -> bool:
    """A build stage's marker agrees with its scenes and files, contents included: a published
    copy damaged in place at the same size is found (its stat changed, so it is read again) and
    the stage runs again, as a scene stage would."""
    return (marker is not None and marker.scene_runs == runs
            and not damaged_outputs(marker, local_size(build_dir),
                                    local_sha256(build_dir, change_time=True)))


def run_build(config: ResolvedConfig, scene_uris: list[str], data_dir: str | Path | DataRoot, *,
              stages: list[str] | None = None, executor: Executor | None = None,
              manifests_dir: str | Path = "manifests", build: str = "default",
              force: bool = False, build_scene_uris: list[str] | None = None,
              selection: Selection | None = None,
              on_start: Callable[[str, str], None] | None = None,
              on_result: Callable[[StageResult], None] | None = None,
              lock_timeout: float = DEFAULT_LOCK_TIMEOUT_S,
              on_progress: ProgressSink | None = None,
              verify_outputs: bool = False) -> BuildReport:
    """Scene stages of ``scene_uris`` through ``executor``, then the build stages (manifest).

    The build stages read every scene of ``build_scene_uris`` (default: ``scene_uris``) that
    finished their needs, so a run over a subset (``--retry-failed``) still publishes the whole
    build. ``on_start(scene_uri or 'build:<name>', stage)`` and ``on_result(StageResult)`` are
    called on this process as tasks start and finish, whatever the executor, and
    ``on_progress(Snapshot)`` as a running scene stage advances. A scene another
    build holds is waited for up to ``lock_timeout`` seconds (:mod:`paradrive.pipeline.locks`).

    ``selection`` is what a caller already decided about splits (``paradrive build`` prints it);
    without one, a training build leaves out the scenes of ``manifest.exclude_splits``.
    """
    from paradrive.stages.ingest import check_uri

    data_dir = DataRoot.of(data_dir)  # absolute: the same folder for workers with another cwd
    scene_stages, build_stages = split_stages(config, stages)
    config.check(scene_stages + build_stages)  # a value no stage can take fails before any runs
    for uri in scene_uris:
        check_uri(uri)  # a malformed URI, or values no ingest takes: a usage error for the build
    # one log given twice is a usage error for the whole build too
    uris = distinct_scenes([SceneInput(uri, uri) for uri in scene_uris])
    # and so is a log that is not there (no scene starts, no lock is taken), and one street twice
    check_present(uris, ingest=config.params.get("ingest"))
    build_uris: list[str] = []
    in_build: set[str] = set()
    for uri in list(build_scene_uris or []) + uris:  # the whole build's order comes first
        if uri not in in_build:
            parse_uri(uri)
            in_build.add(uri)
            build_uris.append(uri)
    if selection is None:
        selection = default_selection(config, uris)
    excluded = {e["scene_uri"] for e in selection.excluded}
    uris = [u for u in uris if u not in excluded]
    build_uris = [u for u in build_uris if u not in excluded]
    executor = executor or LocalExecutor()
    report = BuildReport(excluded=list(selection.excluded))
    if scene_stages:
        def landed(result: StageResult) -> None:
            if on_result:
                on_result(result)
            # a test stops the build here, a stage's result in and the next not yet dispatched
            stop_point(f"landed:{result.stage}:{result.scene_id}")

        tasks = [SceneTask(uri, tuple(scene_stages)) for uri in uris]
        report.results.extend(executor.run(config, tasks, data_dir, RunOptions(
            force=force, on_start=on_start, on_result=landed, locks=LockOptions(build, lock_timeout),
            on_progress=on_progress, verify_outputs=verify_outputs)))
    for stage in build_stages:
        if on_start:
            on_start(f"build:{build}", stage)
        result = executor.run_build_stage(config, stage, functools.partial(
            run_build_stage, config, stage, build_uris, data_dir, Path(manifests_dir), build,
            force=force, record=selection.record()))
        failed_ids = {r.scene_id for r in report.results if r.status == "failed"}
        left_out = [StageResult(sid, stage, "failed", error=(
            f"{stage}: left out of build {build}: the scene has not finished "
            f"{', '.join(needs)}; a plain re-run (without --stages) builds it"))
            for sid, needs in result.summary.get("unfinished", {}).items() if sid not in failed_ids]
        left_out += [StageResult(sid, stage, "failed", error=f"{stage}: left out of build {build}: {why}")
                     for sid, why in result.summary.get("stale", {}).items() if sid not in failed_ids]
        for r in [*left_out, result]:
            report.results.append(r)
            if on_result:
                on_result(r)
    return report


__all__ = ["BuildReport", "default_selection", "run_build", "run_build_stage", "split_stages", "EXIT_OK",
           "EXIT_FAILED", "EXIT_USAGE", "EXIT_PARTIAL", "EXIT_INTERRUPTED", "ConfigError", "StageNotImplemented"]
