"""The manifest stage: one Parquet row per (scene, camera, clip, offset, condition checkpoint).

Reads ``<data>/scenes/<scene_id>/clips/clips.json`` of every scene whose clips are done and
publishes ``<manifests>/<build>/``::

    index.json                 the commit record and the pointer: shards, rows, bytes, sha256,
                               fingerprint, scenes, and the version folder they live in
    v-<nnnnnn>/pairs-<nnnnn>.parquet                          rows sorted by pair_id
    v-<nnnnnn>/media/<scene_id>/clips/<camera>/<clip>/<stream>.mp4    the videos the rows reference
    .paradrive/build.json      the builder's marker: only a folder carrying it is ever changed

URIs in the rows and ``shards[].file`` are relative to the version folder, so a version moves or
publishes as one piece. The column reference is ``manifests/SCHEMA.md``.

Publishing: shards and media are written into a new version folder under a temporary name,
which is renamed to ``v-<n+1>`` and then ``index.json`` is replaced by rename: readers see the
old build or the new one, never a mix. A reader that opened a version reads that version to the
end: a publish keeps the version it replaces and every version replaced less than
``manifest.keep_versions_for`` ago, and removes older ones (:func:`kept_versions`). Files this
stage does not own (the runner's ``ledger.sqlite``, ``logs/``) are never touched.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import paradrive
from paradrive import geometry
from paradrive.errors import ParaDriveError, SceneError
from paradrive.io import (PathEscapeError, is_temporary, path_inside, remove_entry, sha256_file, stop_point,
                          temporary_name, write_json)
from paradrive.pairs import (COLUMNS, INDEX_FORMAT, SCHEMA, SCHEMA_VERSION, make_pair_id, media_uri,
                             read_index)
from paradrive.contracts.layout import (BUILD_MARKER, INDEX_JSON, SHARD_PATTERN, VERSION_PREFIX,
                                        BuildLayout, SceneLayout, is_runner_file, is_version,
                                        version_name, version_number)
from paradrive.contracts.records import ClipRecord, ClipsRecord, IndexRecord
from paradrive.streams import stream_transform

if TYPE_CHECKING:
    from paradrive.contracts.params import ManifestParams

# --------------------------------------------------------------------------- clips.json

@dataclass
class MediaFile:
    """One referenced video: where it is in the scene folder and where it goes in the build."""

    src: Path
    uri: str
    sha256: str
    bytes: int


def read_clips(scene_dir: str | Path) -> ClipsRecord:
    """The scene's ``clips/clips.json``; structural problems are SceneErrors naming the field."""
    layout = SceneLayout(Path(scene_dir))
    return ClipsRecord.load(layout.clips_json, layout.scene_id)


def _fail(doc: ClipsRecord, path: Path, what: str, fix: str = "re-run the clip stage for this scene"):
    return SceneError(what, scene_id=doc.scene_id, path=path, fix=fix)


def _poses(value, n: int, doc: ClipsRecord, path: Path, what: str) -> np.ndarray:
    try:
        poses = geometry.as_pose(value)
    except (ValueError, TypeError) as exc:
        raise _fail(doc, path, f"{what}: not a list of 16-float poses ({exc})") from exc
    if poses.shape != (n, 4, 4):
        raise _fail(doc, path, f"{what}: {poses.shape[0] if poses.ndim == 3 else '?'} poses for "
                               f"{n} frames")
    if not geometry.is_rigid(poses).all():
        bad = int(np.flatnonzero(~geometry.is_rigid(poses))[0])
        raise _fail(doc, path, f"{what}: pose of frame {bad} is not a rigid transform (NaN, "
                               f"scale or shear)")
    return poses


def _media_columns(role: str, file: MediaFile | None) -> dict:
    """``<role>_uri``, ``<role>_sha256``, ``<role>_bytes`` of a row (null when there is no file)."""
    return {f"{role}_uri": file and file.uri, f"{role}_sha256": file and file.sha256,
            f"{role}_bytes": file and file.bytes}


class _SceneMedia:
    """The videos one scene's rows reference, each checked once against clips.json."""

    def __init__(self, layout: SceneLayout, doc: ClipsRecord, verify_inputs: bool):
        self.layout, self.doc, self.verify = layout, doc, verify_inputs
        self.files: dict[str, MediaFile] = {}

    def __call__(self, clip: ClipRecord, name: str) -> MediaFile:
        info = clip.streams[name]
        rel, sid = info.file, self.doc.scene_id
        if rel in self.files:  # checked when an earlier row referenced it
            return self.files[rel]
        where = f"clip {clip.camera}/{clip.clip} stream '{name}'"
        try:
            src = path_inside(self.layout.root, rel, f"{where}: file")
        except PathEscapeError as exc:
            raise _fail(self.doc, self.layout.clips_json, str(exc)) from exc
        if not src.is_file():
            raise SceneError(f"{where}: video is missing", scene_id=sid, path=src,
                             fix="re-run the clip stage for this scene")
        size = src.stat().st_size
        if info.bytes != size:
            raise SceneError(f"{where}: video has {size} bytes, clips.json records "
                             f"{info.bytes}", scene_id=sid, path=src,
                             fix="the file changed after the clip stage; re-run it")
        sha = info.sha256
        if self.verify or not sha:
            actual = sha256_file(src)
            if sha and actual != sha:
                raise SceneError(f"{where}: video sha256 {actual[:12]}… does not match "
                                 f"clips.json ({sha[:12]}…)", scene_id=sid, path=src,
                                 fix="the file is corrupt or changed; re-run the clip stage")
            sha = actual
        self.files[rel] = MediaFile(src=src, uri=media_uri(sid, rel), sha256=sha, bytes=size)
        return self.files[rel]


def _base_row(doc: ClipsRecord, clip: ClipRecord) -> dict:
    """The columns every row of ``clip`` shares."""
    fit = doc.fit
    return {
        "schema_version": SCHEMA_VERSION, "dataset": doc.dataset, "scene_id": doc.scene_id,
        "scene_uri": doc.source, "camera": clip.camera, "clip": clip.clip,
        "frame_start": clip.frame_start, "num_frames": clip.num_frames,
        "frame_indices": clip.frame_indices, "timestamps_us": clip.timestamps_us,
        "fps": doc.fps, "width": doc.width, "height": doc.height,
        "intrinsics": doc.cameras[clip.camera].intrinsics,
        "fit_iteration": fit.iteration, "fit_train_psnr": fit.train_psnr,
        "fit_train_ssim": fit.train_ssim, "dynamic_fraction": clip.dynamic_fraction,
    }


def _clip_rows(doc: ClipsRecord, clip: ClipRecord, path: Path, media: _SceneMedia, quality: bool,
               truth) -> list[dict]:
    camera, name, n = clip.camera, clip.clip, clip.num_frames
    if camera not in doc.cameras or len(doc.cameras[camera].intrinsics) != 4:
        raise _fail(doc, path, f"camera '{camera}': intrinsics must be [fx, fy, cx, cy]")
    where = f"clip {camera}/{name}"
    target_c2w = _poses(clip.c2w, n, doc, path, f"{where} c2w")
    targets = [k for k, v in clip.streams.items() if v.kind == "target"]
    if len(targets) != 1:
        raise _fail(doc, path, f"{where}: expected one target stream, found {len(targets)}")
    streams = clip.streams
    sources = sorted((v.offset_m, k) for k, v in streams.items()
                     if v.kind == "source" and v.offset_m is not None)
    base = _base_row(doc, clip)
    target = media(clip, targets[0])
    if truth is not None:  # inference: the recording is the source, shifted renders condition
        rows = []
        for offset, src_name in sources:
            info = streams[src_name]
            iteration = -1 if info.iteration is None else info.iteration
            novel_c2w = _poses(info.c2w, n, doc, path, f"{where} {src_name} c2w")
            cond = media(clip, src_name)
            true_view = truth(clip, offset, novel_c2w)
            if true_view is not None:
                media.files[true_view.uri] = true_view
            psnr = ssim = None
            if true_view is not None and quality:
                psnr, ssim = video_quality(cond.src, true_view.src)
            rows.append({**base,
                "pair_id": make_pair_id(doc.dataset, doc.scene_id, camera, name, offset, iteration),
                "offset_m": offset, "condition_iteration": iteration, "source_iteration": None,
                "source_stream": targets[0], "condition_stream": src_name,
                **_media_columns("source", target), **_media_columns("condition", cond),
                **_media_columns("target", true_view),
                # rel_pose[i] = inv(c2w_novel[i]) . c2w_recorded[i]
                "rel_pose": geometry.relative_pose(novel_c2w, target_c2w).reshape(n, 16)
                .astype(np.float32),
                "target_c2w": novel_c2w.reshape(n, 16),
                "condition_psnr": psnr, "condition_ssim": ssim})
        return rows
    conditions = sorted((v.iteration, k) for k, v in streams.items()
                        if v.kind == "condition" and v.iteration is not None)
    rows = []
    for iteration, cond_name in conditions:
        cond = media(clip, cond_name)
        q = clip.quality.get(cond_name)
        psnr, ssim = (q.psnr, q.ssim) if q else (None, None)
        if q is None and quality:
            psnr, ssim = video_quality(cond.src, target.src)
        for offset, src_name in sources:
            info = streams[src_name]
            source = media(clip, src_name)
            source_c2w = _poses(info.c2w, n, doc, path, f"{where} {src_name} c2w")
            rows.append({**base,
                "pair_id": make_pair_id(doc.dataset, doc.scene_id, camera, name, offset, iteration),
                "offset_m": offset, "condition_iteration": iteration,
                "source_iteration": -1 if info.iteration is None else info.iteration,
                "source_stream": src_name, "condition_stream": cond_name,
                **_media_columns("source", source), **_media_columns("condition", cond),
                **_media_columns("target", target),
                "rel_pose": geometry.relative_pose(target_c2w, source_c2w).reshape(n, 16)
                .astype(np.float32),
                "target_c2w": target_c2w.reshape(n, 16),
                "condition_psnr": psnr, "condition_ssim": ssim})
    return rows


def scene_rows(scene_dir: str | Path, *, verify_inputs: bool = True, quality: bool = True,
               truth=None) -> tuple[list[dict], list[MediaFile], dict]:
    """Rows of one scene, the media files they reference and a short summary.

    Training (``truth`` None): every clip gives (sources x conditions) rows; the target stream
    is shared. Inference: every clip gives one row per shifted stream, whose source is the
    recording and whose condition is that shifted render; ``truth(clip, offset_m, novel_c2w)``
    returns the true novel view's MediaFile, or None where no truth is known.
    Raises SceneError naming clips.json or the offending video when the scene cannot be used.
    """
    layout = SceneLayout(Path(scene_dir))
    doc = read_clips(layout.root)
    path = layout.clips_json
    if doc.scene_id != layout.scene_id:
        raise _fail(doc, path, f"clips.json names scene '{doc.scene_id}' but lives in "
                               f"'{layout.scene_id}'")
    media = _SceneMedia(layout, doc, verify_inputs)
    rows = [row for clip in doc.clips
            for row in _clip_rows(doc, clip, path, media, quality, truth)]
    if not rows:
        raise _fail(doc, path, "no pairs: the scene has no clip with a source and a condition "
                               "stream", fix="check the clip stage's skipped list in clips.json")
    ids = [r["pair_id"] for r in rows]
    if len(set(ids)) != len(ids):
        raise _fail(doc, path, "two streams give the same pair id (repeated offset or checkpoint)")
    summary = {"scene_id": doc.scene_id, "dataset": doc.dataset, "scene_uri": doc.source,
               "scene_dir": str(layout.root.resolve()), "rows": len(rows),
               "cameras": sorted({r["camera"] for r in rows}),
               "clips": sorted({r["clip"] for r in rows}),
               "skipped_clips": [s.model_dump() for s in doc.skipped],
               "transform": "longitudinal" if any(stream_transform(k) == "longitudinal" for clip in doc.clips
                                                  for k in clip.streams) else "lateral"}
    return rows, list(media.files.values()), summary


def video_quality(condition: Path, target: Path) -> tuple[float, float]:
    """Mean PSNR and SSIM over frames of a condition video against its target video."""
    from paradrive.metrics import frames_quality
    from paradrive.video import decode_frames

    return frames_quality(decode_frames(condition), decode_frames(target))


def dynamic_filter(rows: list[dict], max_fraction: float | None) -> tuple[list[dict], dict | None]:
    """The rows whose ``dynamic_fraction`` is at most ``max_fraction`` (a row without one stays),
    and what index.json records of the filter (None when there is no threshold)."""
    if max_fraction is None:
        return rows, None
    kept = [r for r in rows if r["dynamic_fraction"] is None or r["dynamic_fraction"] <= max_fraction]
    dropped = sorted({(r["scene_id"], r["camera"], r["clip"]) for r in rows if r not in kept})
    return kept, {"max_fraction": float(max_fraction), "dropped_rows": len(rows) - len(kept),
                  "dropped_clips": [{"scene_id": s, "camera": c, "clip": k} for s, c, k in dropped]}


# --------------------------------------------------------------------------- shards

def rows_to_table(rows: list[dict]) -> pa.Table:
    """Arrow table in the manifest schema, rows sorted by pair_id."""
    rows = sorted(rows, key=lambda r: r["pair_id"])
    cols: dict[str, Any] = {}
    for name in COLUMNS:
        values = [r[name] for r in rows]
        kind = SCHEMA.field(name).type
        whole = all(v is not None for v in values)
        cols[name] = _number_lists(values, kind) if whole and _numeric_list(kind) else pa.array(values, type=kind)
    return pa.table(cols, schema=SCHEMA)


def _numeric_list(kind: pa.DataType) -> bool:
    """A list of numbers, or of fixed-size lists of numbers (the frame and pose columns)."""
    if not pa.types.is_list(kind):
        return False
    item = kind.value_type
    leaf = item.value_type if pa.types.is_fixed_size_list(item) else item
    return pa.types.is_integer(leaf) or pa.types.is_floating(leaf)


def _number_lists(values: list, kind: pa.DataType) -> pa.Array:
    """A list column built from one numpy array per row, never a Python number per value: a
    paper-size build holds ~4 * 10^8 pose values (115K rows x 121 frames x 2 x 16), minutes
    and gigabytes as Python floats. Values convert exactly as ``pa.array`` converts them."""
    item = kind.value_type
    fixed = pa.types.is_fixed_size_list(item)
    leaf = item.value_type if fixed else item
    width = item.list_size if fixed else 1
    dtype = leaf.to_pandas_dtype()
    arrays = [np.asarray(v, dtype=dtype).reshape(-1, width) for v in values]
    flat = np.concatenate(arrays).reshape(-1) if arrays else np.empty(0, dtype)
    items = pa.array(flat, type=leaf)
    if fixed:
        items = pa.FixedSizeListArray.from_arrays(items, width)
    offsets = np.concatenate([[0], np.cumsum([len(a) for a in arrays])]).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets, pa.int32()), items, type=kind)


def split_rows(table: pa.Table, shard_rows: int, shard_bytes: int | None) -> list[pa.Table]:
    """Contiguous slices of at most ``shard_rows`` rows (and ``shard_bytes`` Arrow bytes)."""
    if shard_rows < 1:
        raise ParaDriveError(f"manifest.shard_rows must be >= 1, got {shard_rows}")
    if shard_bytes is None:
        return [table.slice(i, shard_rows) for i in range(0, table.num_rows, shard_rows)] or [table]
    if shard_bytes < 1:
        raise ParaDriveError(f"manifest.shard_bytes must be >= 1 or null, got {shard_bytes}")
    shards, start, size = [], 0, 0
    for i in range(table.num_rows):
        row_bytes = table.slice(i, 1).nbytes
        if i > start and (i - start >= shard_rows or size + row_bytes > shard_bytes):
            shards.append(table.slice(start, i - start))
            start, size = i, 0
        size += row_bytes
    shards.append(table.slice(start, table.num_rows - start))
    return shards


# --------------------------------------------------------------------------- media

def place_file(src: Path, dst: Path, mode: str, sha256: str | None = None,
               reuse: Path | None = None) -> str:
    """Put ``src`` at ``dst`` by hardlink, copy or symlink; returns what was done.

    ``reuse`` is the same file in the version published before: a copy whose content still
    matches (size and sha256) is linked from there instead of copied again. The file lands by
    rename, so ``dst`` never holds half a file.
    """
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(dst)
    done = mode
    try:
        if mode == "symlink":
            os.symlink(os.path.abspath(src), tmp)
        elif mode == "copy" and _same_content(reuse, src, sha256):
            _link_or_copy(reuse, tmp)  # type: ignore[arg-type]  # _same_content checked it
            done = "kept"
        elif mode == "hardlink":
            done = _link_or_copy(src, tmp)
        elif mode == "copy":
            shutil.copyfile(src, tmp)
        else:
            raise ParaDriveError(f"manifest.media must be hardlink, copy or symlink, got {mode!r}")
        os.replace(tmp, dst)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    return done


def _same_content(old: Path | None, src: Path, sha256: str | None) -> bool:
    if old is None or old.is_symlink() or not old.is_file() or not sha256:
        return False
    return old.stat().st_size == src.stat().st_size and sha256_file(old) == sha256


def _link_or_copy(src: Path, dst: Path) -> str:
    try:
        os.link(src, dst)
        return "hardlink"
    except OSError as exc:  # another file system, or links not allowed: copy instead
        if exc.errno not in (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP, errno.EACCES):
            raise
        shutil.copyfile(src, dst)
        return "copy"


# --------------------------------------------------------------------------- publish

def claim_build_folder(build_dir: str | Path, build: str) -> BuildLayout:
    """The build folder, created with the builder's marker, or an existing one that carries it.

    A folder holding other files and no marker is not the builder's: it is refused, so nothing in
    it is ever deleted or replaced."""
    layout = BuildLayout(Path(build_dir))
    root = layout.root
    if not layout.marker.is_file():
        foreign = sorted(p.name for p in root.iterdir()
                         if not is_runner_file(p.name)) if root.is_dir() else []
        if foreign and _index_doc(layout).get("format") != INDEX_FORMAT:  # not an earlier build
            raise ParaDriveError(
                f"build {build}: {root} holds files the builder did not write "
                f"({', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}) and no "
                f"{BUILD_MARKER}; choose another --build name or --manifests folder")
        root.mkdir(parents=True, exist_ok=True)
        write_json(layout.marker, {"builder": "paradrive", "build": build})
    return layout


@contextlib.contextmanager
def publishing(build_dir: str | Path, build: str, log=None) -> Iterator[BuildLayout]:
    """The claimed build folder (:func:`claim_build_folder`), one publisher at a time.

    Two runs of one build name (a retry started while the first still runs, a build and a
    republish) take turns: each holds ``.paradrive/publish.lock`` (an ``flock``, which the kernel
    drops when its holder dies, even by SIGKILL) from claiming the folder to landing its version.
    The temporaries in the folder are then a killed publisher's, never a live one's, and are
    removed."""
    layout = claim_build_folder(build_dir, build)
    layout.publish_lock.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(layout.publish_lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if log is not None:
                log.warning("manifest: build %s is being published by another run; waiting for it", build)
            fcntl.flock(fd, fcntl.LOCK_EX)
        for stale in layout.root.iterdir():
            if is_temporary(stale.name):
                remove_entry(stale)
        yield layout
    finally:
        os.close(fd)   # drops the lock


@contextlib.contextmanager
def staging_version(build_dir: str | Path, build: str, log=None) -> Iterator[Path]:
    """A new version folder under a temporary name, this run the build's one publisher
    (:func:`publishing`); gone unless :func:`publish` landed it."""
    with publishing(build_dir, build, log) as layout:
        staging = temporary_name(layout.root / VERSION_PREFIX)
        staging.mkdir()
        try:
            yield staging
        finally:
            shutil.rmtree(staging, ignore_errors=True)


def _write_shards(staging: Path, shards: list[pa.Table], params: ManifestParams) -> list[dict]:
    compression = params.compression
    entries = []
    for i, shard in enumerate(shards):
        name = SHARD_PATTERN.format(i)
        pq.write_table(shard, staging / name,
                       compression=None if compression == "none" else compression,
                       row_group_size=max(1, params.row_group_rows))
        entries.append({"file": name, "rows": shard.num_rows,
                        "bytes": (staging / name).stat().st_size,
                        "sha256": sha256_file(staging / name),
                        "first_pair_id": shard.column("pair_id")[0].as_py() if shard.num_rows else None,
                        "last_pair_id": shard.column("pair_id")[-1].as_py() if shard.num_rows else None})
    return entries


def _place_media(staging: Path, media: list[MediaFile], mode: str, previous: Path | None) -> dict:
    placed: dict[str, int] = {}
    first = True
    for m in media:
        # written in place (truth views); paths compared as written: resolving each one costs
        # a system call per path component, minutes over a paper-size build's media
        if os.path.abspath(m.src) == os.path.abspath(staging / m.uri):
            placed["kept"] = placed.get("kept", 0) + 1
            continue
        done = place_file(m.src, staging / m.uri, mode, m.sha256,
                          reuse=previous / m.uri if previous else None)
        placed[done] = placed.get(done, 0) + 1
        if first:
            stop_point("publish:first-media")
            first = False
    return placed


def _index_doc(layout: BuildLayout) -> dict:
    """What ``index.json`` holds now; empty when there is none or it is unreadable."""
    try:
        doc = json.loads(layout.index_json.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _current_version(layout: BuildLayout) -> str | None:
    """The version ``index.json`` names now (None: nothing published, or an unreadable index)."""
    version = _index_doc(layout).get("version")
    return version if isinstance(version, str) and is_version(version) else None


def _land(layout: BuildLayout, staging: Path, index: dict, keep_for: float) -> str:
    """Rename the staged version into place and switch ``index.json`` to it: the one step that
    publishes. The version keeps its own copy of the index, so a reader can open it by name
    for as long as it stays. Then the versions no reader may hold any more go
    (:func:`expire_versions`)."""
    numbers = [version_number(name) for name in layout.versions()]
    version = version_name(max(numbers, default=0) + 1)
    record = IndexRecord.model_validate({**index, "version": version})
    record.save(staging / INDEX_JSON)
    previous = _current_version(layout)
    first = not layout.index_json.exists()   # then no version here was ever published
    os.replace(staging, layout.version(version))
    stop_point("publish:before-switch")
    record.save(layout.index_json)
    stop_point("publish:after-switch")
    expire_versions(layout, keep_for, current=version, previous=previous, first=first)
    return version


def published_at(layout: BuildLayout, version: str) -> float:
    """When ``version`` was published: the time its own index was written (the folder's, for a
    version published before versions kept one)."""
    folder = layout.version(version)
    try:
        return layout.version_index(version).stat().st_mtime
    except FileNotFoundError:
        return folder.stat().st_mtime


def kept_versions(layout: BuildLayout, keep_for: float, *, current: str | None,
                  previous: str | None, first: bool = False, now: float | None = None) -> list[str]:
    """The version folders a publish keeps, oldest first: the ``current`` one, the ``previous``
    one it replaced, and every earlier one replaced less than ``keep_for`` seconds ago (a
    version is replaced when the one after it is published). A version published after the
    previous one that never became current (a publish killed before its switch) no reader can
    hold: it goes, and so does every other one at a ``first`` publish (no index was there
    before it). Without a current version nothing is judged and every folder stays."""
    versions = layout.versions()
    if current is None:
        return versions
    if first:
        return [current]
    number = {v: version_number(v) for v in versions}
    floor = number.get(previous or "", number[current])
    held = [v for v in versions if number[v] <= floor or v == current]
    now = time.time() if now is None else now
    kept = []
    for older, newer in zip(held, held[1:]):
        if older == previous or now - published_at(layout, newer) < keep_for:
            kept.append(older)
    return kept + held[-1:]


def expire_versions(layout: BuildLayout, keep_for: float, *, current: str,
                    previous: str | None, first: bool = False) -> list[str]:
    """Remove the version folders :func:`kept_versions` lets go; returns their names. Each is
    renamed to a temporary name first, so a half-removed folder is never taken for a version
    (and a killed removal is finished by the next publish)."""
    kept = set(kept_versions(layout, keep_for, current=current, previous=previous, first=first))
    gone = [v for v in layout.versions() if v not in kept]
    for name in gone:
        folder = layout.version(name)
        doomed = temporary_name(folder)
        try:
            os.replace(folder, doomed)
        except FileNotFoundError:   # another publish of this build removed it first
            continue
        shutil.rmtree(doomed, ignore_errors=True)
    return gone


def publish(build_dir: str | Path, rows: list[dict], media: list[MediaFile], *,
            scenes: list[dict], skipped: list[dict], params: ManifestParams, fingerprint: str = "",
            build: str | None = None, log=None, selection: dict | None = None,
            data_root: str | Path | None = None, staging: Path | None = None,
            heldout_filter: dict | None = None,
            dynamic_filter: dict | None = None) -> IndexRecord:
    """Write shards, media and index as a new version of the build; returns the index.

    ``staging`` is a folder from :func:`staging_version` that may already hold files (truth
    views); without one, a new one is made. ``selection`` ({exclude_splits, excluded_scenes})
    records which split files left which scenes out of the build. ``data_root`` is the data
    folder the scenes live in: a ``symlink`` build's links may only lead there.
    ``heldout_filter`` ({min_psnr, dropped}): the held-out PSNR threshold and the scenes it left
    out, recorded in the index when set; ``dynamic_filter`` ({max_fraction, dropped_rows,
    dropped_clips}, :func:`dynamic_filter`) likewise."""
    build = build or Path(build_dir).name
    if staging is None:
        with staging_version(build_dir, build) as fresh:
            return publish(build_dir, rows, media, scenes=scenes, skipped=skipped, params=params,
                           fingerprint=fingerprint, build=build, log=log, selection=selection,
                           data_root=data_root, staging=fresh, heldout_filter=heldout_filter,
                           dynamic_filter=dynamic_filter)
    layout = BuildLayout(Path(build_dir))
    table = rows_to_table(rows)
    ids = table.column("pair_id").to_pylist()
    if len(set(ids)) != len(ids):
        raise ParaDriveError("two scenes give the same pair id; scene ids must be unique")
    entries = _write_shards(staging, split_rows(table, params.shard_rows, params.shard_bytes), params)
    current = _current_version(layout)
    mode = params.media
    placed = _place_media(staging, media, mode, layout.version(current) if current else None)
    index = {
        "format": INDEX_FORMAT, "schema_version": SCHEMA_VERSION, "build": build, "version": None,
        "kind": params.kind, "created_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "software": {"paradrive": paradrive.__version__, "pyarrow": pa.__version__},
        "config_fingerprint": fingerprint, "params": params.source, "sort": ["pair_id"],
        "columns": [{"name": f.name, "type": str(f.type)} for f in SCHEMA],
        "shards": entries,
        "totals": {"rows": table.num_rows, "shards": len(entries),
                   "shard_bytes": sum(e["bytes"] for e in entries),
                   "media_files": len(media), "media_bytes": sum(m.bytes for m in media),
                   "scenes": len(scenes), "scenes_skipped": len(skipped)},
        # only a symlink build needs it: its links lead into that folder and nowhere else
        "media": {"mode": mode, "placed": placed,
                  "data_root": str(Path(data_root).resolve()) if data_root and mode == "symlink"
                  else None},
        "scenes": scenes, "skipped_scenes": skipped,
        **(selection or {"exclude_splits": [], "excluded_scenes": []}),
        **({"heldout_filter": heldout_filter} if heldout_filter is not None else {}),
        **({"dynamic_filter": dynamic_filter} if dynamic_filter is not None else {})}
    version = _land(layout, staging, index, params.keep_versions_seconds)
    if log is not None:
        log.info("manifest: %d rows in %d shards, %d media files (%s) in %s", table.num_rows,
                 len(entries), len(media), placed, version)
    return read_index(layout.root)


__all__ = ["MediaFile", "claim_build_folder", "dynamic_filter", "expire_versions", "kept_versions", "published_at",
           "publish", "read_clips", "scene_rows", "place_file",
           "rows_to_table", "split_rows", "staging_version", "video_quality"]
