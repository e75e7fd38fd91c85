"""Run one (scene, stage): lock the scene, skip if up to date, call the stage, record completion.

A stage knows only its work (``run_stage(ctx)``); where it runs is an executor's business. A
completed stage leaves a marker ``<scene_dir>/.paradrive/<stage>.json`` holding the fingerprint
of its parameters, its inputs' fingerprints and the package version, a run id, the run ids of
the markers it needed, and the files it wrote with their sizes, sha256, modification times and
inodes (``outputs``). A stage is up to date when its fingerprint matches, the stages it needs
were not redone since, and every recorded output is there with its size; otherwise it runs
again, and so does every stage after it. (A marker from before ``outputs`` were recorded counts
as up to date while its declared outputs exist.) The whole decision and run happen under the
scene's lock (:mod:`paradrive.pipeline.locks`), so concurrent builds never write a scene at once.

Retention: a stage's ``retention`` switches (``StageSpec.retention``, e.g. ``render.keep_frames``)
let some of its outputs go once every stage that needs it has used them (that stage done or
skipped). The marker then moves those files from ``outputs`` to ``dropped.files`` and records
the run of each stage that used them (``dropped.after``); the stage stays up to date while those
stages are, and runs again, before them, as soon as one of them has to (a changed parameter, a
damaged output). A stage asked to run on outputs that were let go, without the stage that makes
them, fails naming it.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import importlib
import itertools
import json
import logging
import os
import re
import sys
import time
import traceback
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Callable, Iterator

import paradrive
from paradrive.errors import (ConfigError, ParaDriveError, SceneError, StageNotImplemented, missing_extra,
                              os_error_fix)
from paradrive.io import no_room_message, remove_stale_temporaries, sha256_file
from paradrive.pipeline.locks import HeldLock, LockOptions, SceneLocked, scene_lock
from paradrive.pipeline.progress import ProgressSink, StageProgress
from paradrive.contracts.specs import ResolvedConfig, StageSpec, typed_params
from paradrive.contracts.base import StageContext
from paradrive.contracts.layout import MARKER_DIR, DataLayout, SceneLayout
from paradrive.contracts.records import DroppedOutputs, OutputFile, StageMarker
from paradrive.redact import redact
from paradrive.storage import DataRoot, SceneMirror, file_stats, matches
from paradrive.uri import parse_uri



@dataclass
class StageResult:
    scene_id: str
    stage: str
    status: str                  # done | skipped | failed
    seconds: float = 0.0
    error: str = ""
    fingerprint: str = ""
    peak_rss_mb: float = 0.0
    summary: dict = field(default_factory=dict)
    took_over: str = ""          # the dead or expired lock holder this run replaced


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)


def fingerprint(stage: str, params: dict, inputs: dict[str, str], extra: str = "") -> str:
    """sha256 of the stage name, its parameters, its inputs' fingerprints and the version."""
    doc = {"stage": stage, "params": params, "inputs": inputs, "extra": extra,
           "version": paradrive.__version__}
    return hashlib.sha256(_canonical(doc).encode()).hexdigest()[:20]


def marker_path(scene_dir: Path, stage: str) -> Path:
    return SceneLayout(Path(scene_dir)).marker(stage)


def read_marker(scene_dir: Path, stage: str) -> StageMarker | None:
    """The marker of ``stage`` in a scene or build folder (None: not done, or unreadable)."""
    return StageMarker.read(marker_path(scene_dir, stage))


def expand_outputs(patterns: list[str], params: dict) -> list[str]:
    """Declared outputs with ``{param[:fmt]}`` placeholders expanded (list params expand to many)."""
    out: list[str] = []
    for pattern in patterns:
        names = re.findall(r"{(\w+)(?::[^}]*)?}", pattern)
        values = []
        for name in names:
            v = params.get(name)
            values.append(v if isinstance(v, (list, tuple)) else [v])
        for combo in itertools.product(*values):
            out.append(pattern.format(**dict(zip(names, combo))))
    return out


def outputs_present(scene_dir: Path, spec: StageSpec, params: dict,
                    exists: Callable[[str], bool] | None = None) -> list[str]:
    """Declared outputs that are missing (empty list = all there); ``exists(pattern)`` checks
    somewhere else than the local scene folder (a remote listing)."""
    exists = exists or (lambda rel: bool(glob.glob(str(Path(scene_dir) / rel))))
    return [rel for rel in expand_outputs(spec.outputs, params) if not exists(rel)]


def written_outputs(folder: Path, before: dict[str, tuple[int, int]], declared: list[str],
                    hashes: dict[str, str] | None = None) -> dict[str, OutputFile]:
    """What a stage wrote under ``folder``: files new or changed since ``before`` and files its
    declared outputs name, as relative path -> :func:`output_entry` (markers left out). The
    sha256 the stage computed while writing (``hashes``) is kept; the others are read here."""
    out: dict[str, OutputFile] = {}
    for rel, stat in sorted(file_stats(folder).items()):
        if rel.startswith(MARKER_DIR + "/") or (before.get(rel) == stat and not matches(rel, declared)):
            continue
        out[rel] = output_entry(Path(folder) / rel, (hashes or {}).get(rel))
    return out


def output_entry(path: Path, sha256: str | None = None) -> OutputFile:
    """How a marker records one output: its size and sha256, and the modification time (ns) and
    inode the file had when it was hashed. An up-to-date check trusts the sha256 while those
    three are unchanged (:func:`local_sha256`), so a no-op re-run reads no file; any write moves
    the modification time, and a file put in its place has another inode. The stat is taken
    before the hash: a write during hashing shows as a changed time, never as a trusted hash."""
    stat = path.stat()
    return OutputFile(bytes=stat.st_size, sha256=sha256 or sha256_file(path),
                      mtime_ns=stat.st_mtime_ns, inode=stat.st_ino, ctime_ns=stat.st_ctime_ns)


def damaged_outputs(marker: StageMarker | None, size_of: Callable[[str], int | None],
                    sha_of: Callable[[str, OutputFile], str | None] | None = None) -> dict[str, str]:
    """The recorded outputs of ``marker`` that are missing or changed: rel -> what is wrong.
    Sizes always; with ``sha_of(rel, recorded)``, the content of each file whose size still
    matches."""
    problems = {}
    for rel, info in ((marker.outputs if marker else None) or {}).items():
        size = size_of(rel)
        if size is None:
            problems[rel] = f"{rel} is missing"
        elif size != info.bytes:
            problems[rel] = f"{rel} is {size} bytes, {info.bytes} when written"
        elif sha_of is not None and info.sha256 and sha_of(rel, info) != info.sha256:
            problems[rel] = f"{rel} has changed since it was written (sha256 differs, same size)"
    return problems


def local_size(folder: Path) -> Callable[[str], int | None]:
    """``size_of(rel)`` under ``folder`` (None: not there). Paths are joined as strings: an
    up-to-date check stats every output of every scene, and building a Path per file cost more
    than the stat itself."""
    base = os.fspath(folder)

    def size_of(rel: str) -> int | None:
        try:
            return os.stat(os.path.join(base, rel)).st_size
        except (FileNotFoundError, NotADirectoryError):
            return None
    return size_of


def local_sha256(folder: Path, *, trust_stat: bool = True,
                 change_time: bool = False) -> Callable[[str, OutputFile], str | None]:
    """``sha_of(rel, recorded)``: the sha256 of an output as it is now (None: not a file).

    With ``trust_stat`` a file whose size, modification time and inode are those ``recorded``
    (:func:`output_entry`) keeps its recorded sha256 without being read: a no-op check of a
    paper-size scene's clips then costs a stat per file instead of reading ~0.3 GB. Without it
    (``--verify-outputs``) every file is read. A marker written before the stat was recorded
    has its files read. ``change_time``: the change time must be the recorded one too, which
    no program can set back, so a write whose modification time was put back (``touch -d``,
    ``os.utime``) is found; for a build's shards, not a scene's clips, whose change time moves
    each time a publish links them."""
    def sha_of(rel: str, recorded: OutputFile) -> str | None:
        path = Path(folder) / rel
        try:
            stat = path.stat()
            if trust_stat and (stat.st_size, stat.st_mtime_ns, stat.st_ino) == (
                    recorded.bytes, recorded.mtime_ns, recorded.inode) and not (
                    change_time and recorded.ctime_ns is not None
                    and stat.st_ctime_ns != recorded.ctime_ns):
                return recorded.sha256
            return sha256_file(path)
        except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
            return None
    return sha_of


def hashes_checked(config: ResolvedConfig, stage: str, verify_outputs: bool = False) -> bool:
    """Whether deciding that ``stage`` is up to date checks its outputs' sha256, not only
    their sizes: always for the stages a build stage publishes from (the clips, so that a
    same-size damage never reaches a manifest), for every stage with ``verify_outputs``. The
    check reads a file only when its stat differs from the marker's (:func:`local_sha256`);
    ``verify_outputs`` reads every one."""
    specs = config.registry().specs
    return verify_outputs or any(stage in s.needs for s in specs.values() if s.scope == "build")


def stale_reason(marker: StageMarker | None, fp: str, upstream: dict[str, StageMarker],
                 size_of: Callable[[str], int | None], missing_declared: Callable[[], list[str]],
                 sha_of: Callable[[str, OutputFile], str | None] | None = None) -> str:
    """Why a stage is not up to date ('' when it is): see the module doc."""
    if marker is None:
        return "not run yet"
    if marker.fingerprint != fp:
        return "parameters or inputs changed"
    for need, up in upstream.items():
        if (marker.upstream_runs or {}).get(need) != up.run:
            return f"'{need}' was redone since"
    if marker.outputs is not None:
        damaged = list(damaged_outputs(marker, size_of, sha_of).values())
        if not damaged:
            return ""
        return damaged[0] + (f" (and {len(damaged) - 1} more)" if len(damaged) > 1 else "")
    missing = missing_declared()
    return f"declared output {missing[0]} is missing" if missing else ""


def why_stale(config: ResolvedConfig, stage: str, scene_uri: str, scene_dir: Path,
              size_of: Callable[[str], int | None],
              exists: Callable[[str], bool] | None = None) -> str:
    """Why (scene, stage) must run ('' when it is up to date), outputs let go included."""
    try:
        fp, upstream = stage_fingerprint(config, stage, scene_uri, scene_dir)
    except ConfigError as exc:
        return str(exc)
    return _stale(config, stage, scene_uri, scene_dir, read_marker(scene_dir, stage), fp, upstream,
                  size_of, exists)


def _stale(config: ResolvedConfig, stage: str, scene_uri: str, scene_dir: Path,
           marker: StageMarker | None, fp: str, upstream: dict[str, StageMarker],
           size_of: Callable[[str], int | None], exists: Callable[[str], bool] | None,
           sha_of: Callable[[str, OutputFile], str | None] | None = None) -> str:
    specs = config.registry().specs
    reason = stale_reason(marker, fp, upstream, size_of,
                          lambda: outputs_present(scene_dir, specs[stage], config.params[stage], exists),
                          sha_of)
    if reason or marker is None or not marker.dropped:
        return reason
    dropped = marker.dropped
    for user, run in dropped.after.items():
        why = "it is no longer a stage"
        if user in specs:
            why = why_stale(config, user, scene_uri, scene_dir, size_of, exists)
        used = read_marker(scene_dir, user)
        if not why and (used.run if used else None) != run:
            why = "it ran again since"
        if why:
            return (f"{len(dropped.files)} output(s) were let go by its retention policy and "
                    f"'{user}' needs them again ({why})")
    return ""


def release_outputs(config: ResolvedConfig, stage: str, scene_dir: Path,
                    mirror: SceneMirror | None, log: logging.Logger) -> None:
    """After ``stage`` is done or up to date: let go the outputs of the stages it needs whose
    retention switches are off, once every stage needing them has used this run of them. The
    marker says so first, then the files go (a crash between leaves files, never a lie)."""
    specs = config.registry().specs
    for need in specs[stage].needs:
        patterns = specs[need].released(config.params[need])
        marker = read_marker(scene_dir, need)
        if not patterns or marker is None or marker.outputs is None:
            continue
        users = {name: read_marker(scene_dir, name) for name, spec in specs.items()
                 if need in spec.needs and spec.scope == "scene"}
        if any(((m.upstream_runs or {}) if m else {}).get(need) != marker.run for m in users.values()):
            continue  # a stage needing them has not used this run's outputs yet
        # what the files held; their stat goes with them (a file made again has another)
        files = {rel: OutputFile(bytes=info.bytes, sha256=info.sha256)
                 for rel, info in marker.outputs.items() if matches(rel, patterns)}
        if not files:
            continue
        before = dict(marker.dropped.files) if marker.dropped else {}
        marker = marker.model_copy(update={
            "outputs": {rel: info for rel, info in marker.outputs.items() if rel not in files},
            "dropped": DroppedOutputs(files={**before, **files},
                                      after={name: m.run for name, m in users.items() if m})})
        try:
            marker.save(marker_path(scene_dir, need))
            if mirror:
                mirror.push(mirror.snapshot(), last=[marker_path(Path(), need).as_posix()])
                mirror.remove(sorted(files))
            remove_files(scene_dir, sorted(files))
        except OSError as exc:  # the stage itself is done; the files stay until a later run
            log.warning("%s: could not let go the outputs of %s: %s", stage, need, exc)
            continue
        log.info("%s: %d file(s) of %s let go (%.1f MB; retention: %s)", stage, len(files), need,
                 sum(i.bytes for i in files.values()) / 1e6,
                 ", ".join(k for k in specs[need].retention if config.params[need][k] is False))


def remove_files(folder: Path, rels: list[str]) -> None:
    """Delete files under ``folder`` and the folders they leave empty."""
    parents: set[Path] = set()
    for rel in rels:
        (folder / rel).unlink(missing_ok=True)
        parents.update((folder / rel).parents)
    for parent in sorted(parents, key=lambda p: len(p.parts), reverse=True):
        if parent != folder and folder in parent.parents:
            with contextlib.suppress(OSError):  # not empty: other files still live there
                parent.rmdir()


def peak_rss_mb() -> float:
    """:func:`paradrive.metrics.peak_rss_mb`, imported when a stage ends: that module brings torch,
    which ``paradrive status`` and ``plan``, importing the runner, would otherwise wait seconds for."""
    from paradrive.metrics import peak_rss_mb as peak

    return peak()


def _upload(mirror: SceneMirror, before: dict[str, tuple[int, int]], marker_rel: str,
            guard: Callable[[], None], log: logging.Logger, said: str) -> None:
    """A URL root: what the stage wrote, marker last, while the scene's lease is still ours."""
    guard()
    uploaded, deleted = mirror.push(before, last=[marker_rel])
    log.info(said, uploaded, deleted)


def _remove_if_empty(scene_dir: Path, made: bool) -> None:
    if made:
        with contextlib.suppress(OSError):  # not empty: what is there stays
            scene_dir.rmdir()


def scene_dir_for(data_dir: Path, scene_id: str) -> Path:
    """``<data>/scenes/<scene_id>``; an id that is not a plain file name is refused."""
    return SceneLayout.of(data_dir, scene_id).root


def stage_fingerprint(config: ResolvedConfig, stage: str, scene_uri: str,
                      scene_dir: Path) -> tuple[str, dict[str, StageMarker]]:
    """Fingerprint of (scene, stage) and the markers of the stages it needs.

    Raises ConfigError when a needed stage has not completed for this scene.
    """
    spec = config.registry().specs[stage]
    upstream: dict[str, StageMarker] = {}
    inputs: dict[str, str] = {}
    for need in spec.needs:
        marker = read_marker(scene_dir, need)
        if marker is None:
            raise ConfigError(f"stage '{stage}' needs '{need}', which has not completed for "
                              f"{scene_dir.name}; add '{need}' to --stages")
        upstream[need] = marker
        inputs[need] = marker.fingerprint
    extra = scene_uri if spec.needs == [] else ""
    return fingerprint(stage, spec.fingerprinted(config.params[stage]), inputs, extra), upstream


def check_inputs(scene_id: str, stage: str, upstream: dict[str, StageMarker],
                 size_of: Callable[[str], int | None]) -> None:
    """Refuse to run on damaged inputs or inputs a retention policy let go, naming the stage a
    plain re-run redoes first."""
    for need, marker in upstream.items():
        dropped = sorted(marker.dropped.files) if marker.dropped else []
        if dropped:
            raise SceneError(f"{stage} needs the outputs of {need}, and {len(dropped)} of them "
                             f"({dropped[0]}, ...) were let go by {need}'s retention policy",
                             scene_id=scene_id,
                             fix=f"re-run with '{need}' in --stages (a plain re-run makes them "
                                 f"again, then runs {stage})")
        damaged = list(damaged_outputs(marker, size_of).values())
        if damaged:
            raise SceneError(f"{stage} needs the outputs of {need}, and {damaged[0]}",
                             scene_id=scene_id,
                             fix=f"re-run the build with every stage (a plain re-run redoes "
                                 f"{need}, then {stage})")


def admit_scene(config: ResolvedConfig, stage: str, scene_dir: Path) -> None:
    """Before a stage that needs another spends compute on a scene, every scene stage module's
    ``admit(layout, ingested, params)`` (render: can the scene give a clip?) judges what the
    first stage recorded, so a scene that can never give pairs fails now, not after its fit.
    A module that does not load is left to :func:`load_entry` to report."""
    specs = config.registry().specs
    if not specs[stage].needs:
        return
    ingested: dict[str, Any] = {}
    for name in (n for n, s in specs.items() if not s.needs):
        first = read_marker(scene_dir, name)
        ingested.update((first.summary if first else None) or {})
    for name, spec in specs.items():
        try:
            check = getattr(importlib.import_module(spec.entry.partition(":")[0]), "admit", None)
        except ImportError:
            continue
        if spec.scope == "scene" and check is not None:
            check(SceneLayout(scene_dir), ingested, typed_params(spec, config.params[name]))


def load_entry(spec: StageSpec) -> Callable:
    """The stage's ``run`` function; its module's ``Params`` types the parameters it gets."""
    module_name, _, func_name = spec.entry.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name):
            raise StageNotImplemented(
                f"stage '{spec.name}' is declared in {spec.file} but its implementation "
                f"{spec.entry} is not available (module {exc.name} missing)") from exc
        raise
    func = getattr(module, func_name, None)
    if func is None:
        raise StageNotImplemented(f"stage '{spec.name}' is declared in {spec.file} but "
                                  f"{module_name} has no function {func_name}")
    return func


def summary_of(record: Any) -> dict:
    """What a stage's return value says for its marker."""
    if record is None:
        return {}
    return record.summary() if hasattr(record, "summary") else dict(record)


class _Redacting(logging.Filter):
    """Masks credentials (``paradrive.redact``) in every line before it reaches the log file."""

    def __init__(self, options: dict | None):
        super().__init__()
        self.options = options

    def filter(self, record: logging.LogRecord) -> bool:
        with contextlib.suppress(Exception):  # a malformed call is reported by the handler itself
            record.msg, record.args = redact(record.getMessage(), self.options), None
        return True


class _SceneLogFile(logging.FileHandler):
    """The scene's log file; a line that cannot be written there (its disk full) is dropped,
    not printed with a traceback: the stage's own write fails too and says so in one line."""

    def handleError(self, record: logging.LogRecord) -> None:
        if isinstance(sys.exc_info()[1], OSError):
            return
        super().handleError(record)

    def close(self) -> None:
        with contextlib.suppress(OSError):   # what it could not flush, the disk had no room for
            super().close()


@contextlib.contextmanager
def scene_logger(scene_id: str, log_file: Path | None = None,
                 storage_options: dict | None = None) -> Iterator[logging.Logger]:
    """The scene's logger, appending to ``log_file`` while the stage runs (then closed); lines
    lose the credentials of ``storage_options`` and the environment."""
    log = logging.getLogger(f"paradrive.scene.{scene_id}")
    log.setLevel(logging.INFO)
    log.propagate = False  # the console shows results; the per-scene file has the details
    handler = None
    if log_file is not None:
        log_file.parent.mkdir(parents=True, exist_ok=True)
        handler = _SceneLogFile(os.path.abspath(log_file))
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
        handler.addFilter(_Redacting(storage_options))
        log.addHandler(handler)
    try:
        yield log
    finally:
        if handler is not None:
            log.removeHandler(handler)
            handler.close()


def run_scene_stage(config: ResolvedConfig, stage: str, scene_uri: str,
                    data_dir: str | Path | DataRoot, *, force: bool = False,
                    on_progress: ProgressSink | None = None,
                    locks: LockOptions | None = None, verify_outputs: bool = False) -> StageResult:
    """Run (or skip) one stage of one scene. Never raises for bad input: the result says failed.

    ``data_dir`` is a folder or a :class:`~paradrive.storage.DataRoot` (a URL root runs the
    stage on this node's copy of the scene and uploads the result, marker last). The scene's
    lock is held throughout; ``locks`` names the build and how long to wait for it. The stage's
    progress goes to the scene's log and, as it happens, to ``on_progress``
    (:mod:`paradrive.pipeline.progress`). Outputs are checked by size, and by sha256 where
    :func:`hashes_checked` says (``verify_outputs``: every stage's; on a folder root only).
    """
    root = DataRoot.of(data_dir)
    try:
        scene_id = parse_uri(scene_uri).scene_id
    except ParaDriveError as exc:
        return StageResult(scene_id=scene_uri, stage=stage, status="failed", error=str(exc))
    with contextlib.ExitStack() as stack:
        try:
            held = stack.enter_context(scene_lock(root, scene_id, locks))
        except SceneLocked as exc:
            return StageResult(scene_id, stage, "failed", error=str(exc))
        except Exception as exc:  # the lock folder or the lease store (fsspec backends' own errors)
            return StageResult(scene_id, stage, "failed",
                               error=f"scene {scene_id}: {stage}: cannot lock "
                                     f"{root.scene_location(scene_id)}: {type(exc).__name__}: "
                                     f"{exc}; check the data root and re-run")
        if held.read_only:   # the data root refused its lock file: nothing may be written
            return _read_only_stage(config, stage, scene_uri, scene_id, root, force,
                                    verify_outputs, held.read_only)
        try:
            result = _run_locked(config, stage, scene_uri, scene_id, root, force, on_progress,
                                 verify_outputs, held)
        finally:   # however it ended: a scene that never started keeps no lock file
            held.discard = not scene_dir_for(root.local, scene_id).exists()
        result.took_over = held.took_over
        return result


def _read_only_stage(config: ResolvedConfig, stage: str, scene_uri: str, scene_id: str,
                     root: DataRoot, force: bool, verify_outputs: bool, why: str) -> StageResult:
    """(scene, stage) on a data root this process cannot write (``why``: the lock file it was
    refused): up to date, it is skipped as anywhere else, with nothing written (no log line,
    no outputs let go); to run, it fails in one line naming the root and the fix."""
    scene_dir = scene_dir_for(root.local, scene_id)
    fp, marker = "", read_marker(scene_dir, stage)
    try:
        fp, upstream = stage_fingerprint(config, stage, scene_uri, scene_dir)
        sha_of = (local_sha256(scene_dir, trust_stat=not verify_outputs)
                  if hashes_checked(config, stage, verify_outputs) else None)
        reason = "--force" if force else _stale(config, stage, scene_uri, scene_dir, marker, fp,
                                                upstream, local_size(scene_dir), None, sha_of)
    except ConfigError as exc:
        reason = str(exc)
    if not reason:
        return StageResult(scene_id, stage, "skipped", fingerprint=fp,
                           summary=dict((marker.summary if marker else None) or {}))
    return StageResult(scene_id, stage, "failed", fingerprint=fp, error=(
        f"scene {scene_id}: {stage} has to run ({reason}), but the data root {root.local} is "
        f"read-only for this build ({why}); make it writable or pass a --data this user can "
        f"write, then re-run"))


def _run_locked(config: ResolvedConfig, stage: str, scene_uri: str, scene_id: str, root: DataRoot,
                force: bool, on_progress: ProgressSink | None, verify_outputs: bool,
                held: HeldLock) -> StageResult:
    mirror = root.mirror(scene_id)
    if mirror is None:
        return _run_scene_stage(config, stage, scene_uri, scene_id, root, None, force, on_progress,
                                hashes_checked(config, stage, verify_outputs),
                                trust_stat=not verify_outputs, guard=held.check)
    try:
        mirror.pull_log()
        mirror.sync([f"{MARKER_DIR}/*.json"])  # the remote markers are the truth
    except OSError as exc:  # StorageError: names the URL and the fix
        return StageResult(scene_id, stage, "failed", error=f"scene {scene_id}: {stage}: {exc}")
    try:
        # A URL root is checked from one listing (sizes): hashing would download every file.
        result = _run_scene_stage(config, stage, scene_uri, scene_id, root, mirror, force,
                                  on_progress, False, guard=held.check)
    finally:
        with contextlib.suppress(OSError):
            if not held.lost:   # a lost lease writes nothing more there, its log included
                mirror.push_log()
        if root.drop_cache:
            mirror.drop()
    return result


def _run_scene_stage(config: ResolvedConfig, stage: str, scene_uri: str, scene_id: str,
                     root: DataRoot, mirror: SceneMirror | None, force: bool,
                     on_progress: ProgressSink | None, check_hashes: bool, *,
                     trust_stat: bool = True, guard: Callable[[], None] = lambda: None) -> StageResult:
    """Decide, run and mark one (scene, stage) under its lock. ``guard()`` raises once the lock
    is lost (:class:`~paradrive.pipeline.locks.LeaseLost`): it is called at every progress
    report of the stage and before the marker and the upload, so a stage whose lease another
    build took stops before it writes anything more."""
    scene_dir = scene_dir_for(root.local, scene_id)
    with scene_logger(scene_id, DataLayout(root.local).log(scene_id), root.storage_options) as log:
        run = _StageRun(config, stage, scene_uri, scene_id, root, mirror, scene_dir, log)
        t0 = time.time()
        made = not scene_dir.exists()  # a first stage that fails leaves no empty scene folder
        try:
            fp, upstream = stage_fingerprint(config, stage, scene_uri, scene_dir)
            marker = read_marker(scene_dir, stage)
            size_of = (lambda rel: mirror.listing.get(rel, {}).get("size")) if mirror \
                else local_size(scene_dir)
            sha_of = local_sha256(scene_dir, trust_stat=trust_stat) if check_hashes else None
            reason = "--force" if force else _stale(
                config, stage, scene_uri, scene_dir, marker, fp, upstream, size_of,
                mirror.exists if mirror else None, sha_of)
            if not reason:
                log.info("%s: up to date (fingerprint %s), skipped", stage, fp)
                release_outputs(config, stage, scene_dir, mirror, log)
                return StageResult(scene_id, stage, "skipped", fingerprint=fp,
                                   summary=dict((marker.summary if marker else None) or {}))
            log.info("%s: to run: %s", stage, reason)
            check_inputs(scene_id, stage, upstream, size_of)
            func = load_entry(run.spec)
            admit_scene(config, stage, scene_dir)
            before = run.make_room(marker, size_of)
            return run.execute(func, fp, upstream, before, t0, on_progress, guard)
        except (SceneError, ConfigError, StageNotImplemented, OSError, ValueError) as exc:
            return run.failed(exc, t0, made)
        except Exception as exc:  # a bug or an unexpected library error: still never stop other scenes
            return run.crashed(exc, t0, made)


@dataclass
class _StageRun:
    """One (scene, stage) that runs under its lock: the folder made ready for it, the stage
    called, its outputs checked and its marker written (and, on a URL root, uploaded), or its
    failure reported in one line."""

    config: ResolvedConfig
    stage: str
    scene_uri: str
    scene_id: str
    root: DataRoot
    mirror: SceneMirror | None
    scene_dir: Path
    log: logging.Logger
    spec: StageSpec = field(init=False)
    marker_rel: str = field(init=False)   # the marker's path in the scene folder

    def __post_init__(self) -> None:
        self.spec = self.config.registry().specs[self.stage]
        self.marker_rel = marker_path(Path(), self.stage).as_posix()

    def make_room(self, marker: StageMarker | None, size_of: Callable[[str], int | None]) -> dict:
        """The scene folder ready for the stage: its marker gone (here and on the remote), what it
        reads brought from a URL root, damaged outputs and stale temporaries removed. Returns the
        files there before it runs."""
        self.scene_dir.mkdir(parents=True, exist_ok=True)
        marker_path(self.scene_dir, self.stage).unlink(missing_ok=True)
        if self.mirror:
            self.mirror.withdraw(self.marker_rel)
            pulled = self.mirror.pull(self.spec.reads)
            self.log.info("%s: %d file(s) brought from %s", self.stage, pulled,
                          self.root.scene_location(self.scene_id))
        # A stage may resume from what it finds (a fit's state.pt), never from a damaged
        # output, nor, on a URL root, a cached copy of one the remote lost. Whether a stage
        # is done is decided here only, never by the stage itself.
        for rel in damaged_outputs(marker, size_of):
            (self.scene_dir / rel).unlink(missing_ok=True)
        remove_stale_temporaries(self.scene_dir)
        return file_stats(self.scene_dir)

    def execute(self, func: Callable[[StageContext], Any], fp: str, upstream: dict, before: dict,
                t0: float, on_progress: ProgressSink | None, guard: Callable[[], None]) -> StageResult:
        """Call the stage; check its declared outputs are there; write its marker (the lock
        checked first) and upload on a URL root; let go of what retention releases."""
        stage, scene_dir, params = self.stage, self.scene_dir, self.config.params[self.stage]
        self.log.info("%s: started (fingerprint %s)", stage, fp)
        ctx = StageContext(stage=stage, scene_uri=self.scene_uri, scene_id=self.scene_id,
                           layout=SceneLayout(scene_dir), data_dir=self.root.local,
                           params=typed_params(self.spec, params), log=self.log, upstream=upstream,
                           build_params=self.config.params,
                           progress=StageProgress(self.scene_id, stage, self.log, on_progress, guard=guard))
        summary = summary_of(func(ctx))
        missing = outputs_present(scene_dir, self.spec, params)
        if missing:
            raise StageNotImplemented(f"stage '{stage}' finished without writing its declared "
                                      f"outputs: {', '.join(missing[:5])}")
        seconds = time.time() - t0
        guard()
        StageMarker(stage=stage, scene_id=self.scene_id, scene_uri=self.scene_uri, fingerprint=fp,
                    params=params, inputs={k: v.fingerprint for k, v in upstream.items()},
                    version=paradrive.__version__, seconds=round(seconds, 3),
                    finished_at=time.strftime("%Y-%m-%dT%H:%M:%S"), summary=summary,
                    run=uuid.uuid4().hex, upstream_runs={k: v.run for k, v in upstream.items()},
                    outputs=written_outputs(scene_dir, before, expand_outputs(self.spec.outputs, params),
                                            ctx.hashes)).save(marker_path(scene_dir, stage))
        if self.mirror:
            _upload(self.mirror, before, self.marker_rel, guard, self.log, f"{stage}: %d file(s) "
                    f"uploaded to {self.root.scene_location(self.scene_id)}, %d removed there")
        release_outputs(self.config, stage, scene_dir, self.mirror, self.log)
        self.log.info("%s: done in %.1f s", stage, seconds)
        return StageResult(self.scene_id, stage, "done", seconds=seconds, fingerprint=fp,
                           peak_rss_mb=peak_rss_mb(), summary=summary)

    def failed(self, exc: Exception, t0: float, made: bool, message: str | None = None) -> StageResult:
        """The failed result of bad input or a failed write: one line naming the scene (an
        error that does not name it gets its type and the fix an OSError calls for)."""
        if message is None:
            message = str(exc)
            if not isinstance(exc, ParaDriveError):
                message = no_room_message(
                    exc, f"scene {self.scene_id}: {self.stage}", self.scene_dir,
                    elsewhere="pass another --cache" if self.root.remote else "pass another --data"
                ) or (f"scene {self.scene_id}: {self.stage} failed: {type(exc).__name__}: {exc}"
                      f"{os_error_fix(exc, self.scene_dir)}")
            message = redact(message, self.root.storage_options)
        self.log.error("%s: failed: %s", self.stage, message)
        _remove_if_empty(self.scene_dir, made)
        return StageResult(self.scene_id, self.stage, "failed", seconds=time.time() - t0,
                           error=message, peak_rss_mb=peak_rss_mb())

    def crashed(self, exc: Exception, t0: float, made: bool) -> StageResult:
        """The failed result of anything else: an optional package the scene needs is named with
        its extra; a bug's traceback goes to the scene's log."""
        extra = missing_extra(exc) if isinstance(exc, ModuleNotFoundError) else None
        if extra is not None:  # an optional package this scene needs (pycolmap for video:)
            return self.failed(exc, t0, made, f"scene {self.scene_id}: {self.stage}: {extra}")
        self.log.error("%s: crashed:\n%s", self.stage, traceback.format_exc())
        _remove_if_empty(self.scene_dir, made)
        return StageResult(self.scene_id, self.stage, "failed", seconds=time.time() - t0,
                           error=redact(f"scene {self.scene_id}: {self.stage} crashed: "
                                        f"{type(exc).__name__}: {exc} (traceback in "
                                        f"{self.root}/logs/{self.scene_id}.log)", self.root.storage_options),
                           peak_rss_mb=peak_rss_mb())
