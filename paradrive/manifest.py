"""The manifest stage: one Parquet row per (scene, camera, clip, offset, condition checkpoint).

Reads ``<data>/scenes/<scene_id>/clips/clips.json`` of every scene whose clips are done and
publishes ``<manifests>/<build>/``::

    index.json                 the commit record: shards, rows, bytes, sha256, fingerprint, scenes
    pairs-<nnnnn>.parquet      rows sorted by pair_id
    media/<scene_id>/clips/<camera>/<clip>/<stream>.mp4    the videos the rows reference

URIs in the rows are relative to the build folder, so the folder moves or publishes as one piece.
The column reference is ``manifests/SCHEMA.md``.

Publishing: shards are written into a hidden staging folder, media files are linked one by one
(each by rename), then ``index.json`` is withdrawn, the shards are renamed into place and a new
``index.json`` lands last. Readers open a build through its index; a folder without one is being
published (or was never built). Files this stage does not own (the runner's ``ledger.sqlite``,
``logs/``) are never touched.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import paradrive
from paradrive import geometry
from paradrive.errors import ParaDriveError, SceneError
from paradrive.io import (PathEscapeError, check_relative, path_inside, sha256_file, temporary_name,
                          write_json)

SCHEMA_VERSION = 1
CLIPS_SCHEMA_VERSION = 1
INDEX_NAME = "index.json"
MEDIA_DIR = "media"
SHARD_PATTERN = "pairs-{:05d}.parquet"
STAGING_PREFIX = ".manifest-staging"

SCHEMA = pa.schema([
    ("schema_version", pa.int32()),
    ("pair_id", pa.string()),
    ("dataset", pa.string()),
    ("scene_id", pa.string()),
    ("scene_uri", pa.string()),
    ("camera", pa.string()),
    ("clip", pa.string()),
    ("frame_start", pa.int32()),
    ("num_frames", pa.int32()),
    ("frame_indices", pa.list_(pa.int32())),
    ("timestamps_us", pa.list_(pa.int64())),
    ("fps", pa.float64()),
    ("width", pa.int32()),
    ("height", pa.int32()),
    ("intrinsics", pa.list_(pa.float64(), 4)),
    ("offset_m", pa.float64()),
    ("condition_iteration", pa.int32()),
    ("source_iteration", pa.int32()),
    ("source_stream", pa.string()),
    ("condition_stream", pa.string()),
    ("source_uri", pa.string()),
    ("source_sha256", pa.string()),
    ("source_bytes", pa.int64()),
    ("condition_uri", pa.string()),
    ("condition_sha256", pa.string()),
    ("condition_bytes", pa.int64()),
    ("target_uri", pa.string()),
    ("target_sha256", pa.string()),
    ("target_bytes", pa.int64()),
    ("rel_pose", pa.list_(pa.list_(pa.float32(), 16))),
    ("target_c2w", pa.list_(pa.list_(pa.float64(), 16))),
    ("condition_psnr", pa.float64()),
    ("condition_ssim", pa.float64()),
    ("fit_iteration", pa.int32()),
    ("fit_train_psnr", pa.float64()),
    ("fit_train_ssim", pa.float64()),
])

COLUMNS = tuple(SCHEMA.names)


# --------------------------------------------------------------------------- names

def offset_token(offset_m: float) -> str:
    """``+2m``, ``-1m``, ``+1.5m``: the offset as written in names and pair ids."""
    return f"{float(offset_m):+g}m"


def make_pair_id(dataset: str, scene_id: str, camera: str, clip: str, offset_m: float,
                 condition_iteration: int) -> str:
    """``<dataset>/<scene_id>/<camera>/<clip>/<+2m>/<000500>``: stable across builds."""
    return (f"{dataset}/{scene_id}/{camera}/{clip}/{offset_token(offset_m)}/"
            f"{int(condition_iteration):06d}")


def media_uri(scene_id: str, file: str) -> str:
    """Build-relative URI of a scene file (``clips/...`` relative to the scene folder)."""
    return f"{MEDIA_DIR}/{scene_id}/{file}"


URI_COLUMNS = ("source_uri", "condition_uri", "target_uri")


def check_row_uris(columns: dict, where: str) -> None:
    """Every URI of ``columns`` ({pair_id: [...], source_uri: [...], ...}) is a relative,
    normalised path inside the build; else a PathEscapeError naming ``where``, the row and column."""
    checked: set = set()  # rows share videos: a target serves every offset and checkpoint
    for column in URI_COLUMNS:
        for pair_id, uri in zip(columns["pair_id"], columns[column]):
            if uri is not None and uri not in checked:  # an inference row may have no target
                check_relative(uri, f"{where}: row {pair_id} column {column}")
                checked.add(uri)


def build_file(build_dir: str | Path, uri: object, what: str, index: dict) -> Path:
    """The file a build-relative ``uri`` names, checked to stay inside the build.

    A build published with ``media: symlink`` links each media file to the scene's own clip in
    the data folder: such a link may lead out, but only to ``<...>/<scene_id>/<file>`` named
    like the URI, never to an arbitrary file.
    """
    linked = (index.get("media") or {}).get("mode") == "symlink"
    tail = Path(str(uri)).parts[1:] if str(uri).startswith(MEDIA_DIR + "/") else ()

    def scene_clip(resolved: Path) -> bool:
        return linked and len(tail) >= 2 and resolved.parts[-len(tail):] == tail

    return path_inside(build_dir, uri, what, may_lead_out=scene_clip)


# --------------------------------------------------------------------------- clips.json

@dataclass
class MediaFile:
    """One referenced video: where it is in the scene folder and where it goes in the build."""

    src: Path
    uri: str
    sha256: str
    bytes: int


def read_clips(scene_dir: str | Path) -> dict:
    """Parse and check ``<scene_dir>/clips/clips.json``; structural problems are SceneErrors."""
    scene_dir = Path(scene_dir)
    path = scene_dir / "clips" / "clips.json"
    sid = scene_dir.name
    if not path.is_file():
        raise SceneError("clips.json is missing", scene_id=sid, path=path,
                         fix="run the clip stage for this scene first")
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SceneError(f"clips.json is not valid JSON ({exc})", scene_id=sid, path=path,
                         fix="re-run the clip stage for this scene") from exc
    if doc.get("schema_version") != CLIPS_SCHEMA_VERSION:
        raise SceneError(f"clips.json schema_version {doc.get('schema_version')!r} is not "
                         f"{CLIPS_SCHEMA_VERSION}", scene_id=sid, path=path,
                         fix="re-run the clip stage with this version of paradrive")
    for key in ("scene_id", "dataset", "fps", "width", "height", "cameras", "clips"):
        if key not in doc:
            raise SceneError(f"clips.json has no '{key}'", scene_id=sid, path=path,
                             fix="re-run the clip stage for this scene")
    return doc


def _fail(doc: dict, path: Path, what: str, fix: str = "re-run the clip stage for this scene"):
    return SceneError(what, scene_id=doc.get("scene_id"), path=path, fix=fix)


def _poses(value, n: int, doc: dict, path: Path, what: str) -> np.ndarray:
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


def scene_rows(scene_dir: str | Path, *, verify_inputs: bool = True, quality: bool = True,
               truth=None) -> tuple[list[dict], list[MediaFile], dict]:
    """Rows of one scene, the media files they reference and a short summary.

    Training (``truth`` None): every clip gives (sources x conditions) rows; the target stream
    is shared. Inference: every clip gives one row per shifted stream, whose source is the
    recording and whose condition is that shifted render; ``truth(clip, offset_m, novel_c2w)``
    returns the true novel view's MediaFile, or None where no truth is known.
    Raises SceneError naming clips.json or the offending video when the scene cannot be used.
    """
    scene_dir = Path(scene_dir)
    doc = read_clips(scene_dir)
    path = scene_dir / "clips" / "clips.json"
    sid, dataset = str(doc["scene_id"]), str(doc["dataset"])
    if sid != scene_dir.name:
        raise _fail(doc, path, f"clips.json names scene '{sid}' but lives in '{scene_dir.name}'")
    fit = doc.get("fit") or {}
    media: dict[str, MediaFile] = {}

    def stream_file(clip: dict, name: str, info: dict) -> MediaFile:
        rel = str(info.get("file", ""))
        where = f"clip {clip['camera']}/{clip['clip']} stream '{name}'"
        try:
            src = path_inside(scene_dir, rel, f"{where}: file")
        except PathEscapeError as exc:
            raise _fail(doc, path, str(exc)) from exc
        if rel in media:
            return media[rel]
        if not src.is_file():
            raise SceneError(f"{where}: video is missing", scene_id=sid, path=src,
                             fix="re-run the clip stage for this scene")
        size = src.stat().st_size
        if "bytes" in info and int(info["bytes"]) != size:
            raise SceneError(f"{where}: video has {size} bytes, clips.json records "
                             f"{info['bytes']}", scene_id=sid, path=src,
                             fix="the file changed after the clip stage; re-run it")
        sha = str(info.get("sha256") or "")
        if verify_inputs or not sha:
            actual = sha256_file(src)
            if sha and actual != sha:
                raise SceneError(f"{where}: video sha256 {actual[:12]}… does not match "
                                 f"clips.json ({sha[:12]}…)", scene_id=sid, path=src,
                                 fix="the file is corrupt or changed; re-run the clip stage")
            sha = actual
        media[rel] = MediaFile(src=src, uri=media_uri(sid, rel), sha256=sha, bytes=size)
        return media[rel]

    rows: list[dict] = []
    cameras = doc["cameras"]
    for clip in doc["clips"]:
        try:
            camera, name = str(clip["camera"]), str(clip["clip"])
            n = int(clip["num_frames"])
            streams = clip["streams"]
            intr = [float(x) for x in cameras[camera]["intrinsics"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise _fail(doc, path, f"clip entry is malformed ({type(exc).__name__}: {exc})") from exc
        if len(intr) != 4:
            raise _fail(doc, path, f"camera '{camera}': intrinsics must be [fx, fy, cx, cy]")
        where = f"clip {camera}/{name}"
        target_c2w = _poses(clip.get("c2w"), n, doc, path, f"{where} c2w")
        targets = [k for k, v in streams.items() if v.get("kind") == "target"]
        if len(targets) != 1:
            raise _fail(doc, path, f"{where}: expected one target stream, found {len(targets)}")
        target = stream_file(clip, targets[0], streams[targets[0]])
        conditions = sorted(((int(v["iteration"]), k) for k, v in streams.items()
                             if v.get("kind") == "condition"))
        sources = sorted(((float(v["offset_m"]), k) for k, v in streams.items()
                          if v.get("kind") == "source"))
        frame_indices = [int(i) for i in clip.get("frame_indices") or
                         range(int(clip["frame_start"]), int(clip["frame_start"]) + n)]
        base = {
            "schema_version": SCHEMA_VERSION, "dataset": dataset, "scene_id": sid,
            "scene_uri": str(doc.get("source", "")), "camera": camera, "clip": name,
            "frame_start": int(clip["frame_start"]), "num_frames": n,
            "frame_indices": frame_indices, "timestamps_us": [int(t) for t in clip.get("timestamps_us") or []],
            "fps": float(doc["fps"]), "width": int(doc["width"]), "height": int(doc["height"]),
            "intrinsics": intr,
            "fit_iteration": None if fit.get("iteration") is None else int(fit["iteration"]),
            "fit_train_psnr": None if fit.get("train_psnr") is None else float(fit["train_psnr"]),
            "fit_train_ssim": None if fit.get("train_ssim") is None else float(fit["train_ssim"]),
        }
        if truth is not None:  # inference: the recording is the source, shifted renders condition
            for offset, src_name in sources:
                info = streams[src_name]
                novel_c2w = _poses(info.get("c2w"), n, doc, path, f"{where} {src_name} c2w")
                cond = stream_file(clip, src_name, info)
                true_view = truth(clip, offset, novel_c2w)
                if true_view is not None:
                    media[true_view.uri] = true_view
                psnr = ssim = None
                if true_view is not None and quality:
                    psnr, ssim = video_quality(cond.src, true_view.src)
                rows.append({**base,
                    "pair_id": make_pair_id(dataset, sid, camera, name, offset,
                                            int(info.get("iteration", -1))),
                    "offset_m": offset, "condition_iteration": int(info.get("iteration", -1)),
                    "source_iteration": None,
                    "source_stream": targets[0], "condition_stream": src_name,
                    **_media_columns("source", target), **_media_columns("condition", cond),
                    **_media_columns("target", true_view),
                    # rel_pose[i] = inv(c2w_novel[i]) . c2w_recorded[i]
                    "rel_pose": geometry.relative_pose(novel_c2w, target_c2w).reshape(n, 16)
                    .astype(np.float32),
                    "target_c2w": novel_c2w.reshape(n, 16),
                    "condition_psnr": psnr, "condition_ssim": ssim})
            continue
        clip_quality = clip.get("quality") or {}
        for iteration, cond_name in conditions:
            cond = stream_file(clip, cond_name, streams[cond_name])
            q = clip_quality.get(cond_name) or {}
            psnr, ssim = q.get("psnr"), q.get("ssim")
            if (psnr is None or ssim is None) and quality:
                psnr, ssim = video_quality(cond.src, target.src)
            for offset, src_name in sources:
                info = streams[src_name]
                source = stream_file(clip, src_name, info)
                source_c2w = _poses(info.get("c2w"), n, doc, path, f"{where} {src_name} c2w")
                rel = geometry.relative_pose(target_c2w, source_c2w)
                rows.append({**base,
                    "pair_id": make_pair_id(dataset, sid, camera, name, offset, iteration),
                    "offset_m": offset, "condition_iteration": iteration,
                    "source_iteration": int(info.get("iteration", -1)),
                    "source_stream": src_name, "condition_stream": cond_name,
                    **_media_columns("source", source), **_media_columns("condition", cond),
                    **_media_columns("target", target),
                    "rel_pose": rel.reshape(n, 16).astype(np.float32),
                    "target_c2w": target_c2w.reshape(n, 16),
                    "condition_psnr": None if psnr is None else float(psnr),
                    "condition_ssim": None if ssim is None else float(ssim),
                })
    if not rows:
        raise _fail(doc, path, "no pairs: the scene has no clip with a source and a condition "
                               "stream", fix="check the clip stage's skipped list in clips.json")
    ids = [r["pair_id"] for r in rows]
    if len(set(ids)) != len(ids):
        raise _fail(doc, path, "two streams give the same pair id (repeated offset or checkpoint)")
    summary = {"scene_id": sid, "dataset": dataset, "scene_uri": str(doc.get("source", "")),
               "scene_dir": str(scene_dir.resolve()), "rows": len(rows),
               "cameras": sorted({r["camera"] for r in rows}),
               "clips": sorted({r["clip"] for r in rows}),
               "skipped_clips": list(doc.get("skipped") or [])}
    return rows, list(media.values()), summary


def video_quality(condition: Path, target: Path) -> tuple[float, float]:
    """Mean PSNR and SSIM over frames of a condition video against its target video."""
    import torch

    from paradrive.data import decode_frames
    from paradrive.metrics import psnr, ssim

    a = torch.from_numpy(decode_frames(condition)).float() / 255.0
    b = torch.from_numpy(decode_frames(target)).float() / 255.0
    n = min(len(a), len(b))
    with torch.no_grad():
        return float(psnr(a[:n], b[:n]).mean()), float(ssim(a[:n], b[:n]).mean())


# --------------------------------------------------------------------------- shards

def rows_to_table(rows: list[dict]) -> pa.Table:
    """Arrow table in the manifest schema, rows sorted by pair_id."""
    rows = sorted(rows, key=lambda r: r["pair_id"])
    cols: dict[str, Any] = {}
    for name in COLUMNS:
        values = [r[name] for r in rows]
        if name in ("rel_pose", "target_c2w"):
            values = [[list(map(float, frame)) for frame in v] for v in values]
        cols[name] = pa.array(values, type=SCHEMA.field(name).type)
    return pa.table(cols, schema=SCHEMA)


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

def place_file(src: Path, dst: Path, mode: str, sha256: str | None = None) -> str:
    """Put ``src`` at ``dst`` by hardlink, copy or symlink; returns what was done.

    An existing ``dst`` with the same content (same inode, or same size and sha256) is kept, so
    re-publishing leaves unchanged media alone. Every change lands by rename.
    """
    dst.parent.mkdir(parents=True, exist_ok=True)
    if mode == "symlink":
        target = os.path.abspath(src)
        if dst.is_symlink() and os.readlink(dst) == target:
            return "kept"
    elif dst.exists() and not dst.is_symlink():
        a, b = src.stat(), dst.stat()
        if (a.st_ino, a.st_dev) == (b.st_ino, b.st_dev):
            return "kept"
        if a.st_size == b.st_size and sha256 and sha256_file(dst) == sha256:
            return "kept"
    tmp = temporary_name(dst)
    done = mode
    try:
        if mode == "symlink":
            os.symlink(os.path.abspath(src), tmp)
        elif mode == "hardlink":
            try:
                os.link(src, tmp)
            except OSError as exc:  # another file system, or links not allowed: copy instead
                if exc.errno not in (errno.EXDEV, errno.EPERM, errno.EMLINK, errno.ENOTSUP,
                                     errno.EACCES):
                    raise
                shutil.copyfile(src, tmp)
                done = "copy"
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


# --------------------------------------------------------------------------- reading

def read_index(build_dir: str | Path) -> dict:
    """The build's ``index.json``; a clear error when the folder holds no published build."""
    build_dir = Path(build_dir)
    path = build_dir / INDEX_NAME
    if not build_dir.is_dir():
        raise ParaDriveError(f"build folder {build_dir} does not exist; pass the folder "
                             f"<manifests>/<build> that `paradrive build` wrote")
    if not path.is_file():
        raise ParaDriveError(f"{path} is missing: the build is being published or was never "
                             f"built; wait for `paradrive build` to finish, or run it")
    try:
        index = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ParaDriveError(f"{path} is not valid JSON ({exc}); re-run the manifest stage "
                             f"(paradrive build --stages manifest --force)") from exc
    if index.get("format") != "paradrive-pairs":
        raise ParaDriveError(f"{path} is not a paradrive pair index (format "
                             f"{index.get('format')!r})")
    if index.get("schema_version") != SCHEMA_VERSION:
        raise ParaDriveError(f"{path}: manifest schema_version {index.get('schema_version')!r} "
                             f"is not {SCHEMA_VERSION}; rebuild it with this paradrive version")
    return index


def shard_paths(build_dir: str | Path, index: dict | None = None) -> list[Path]:
    build_dir = Path(build_dir)
    index = index or read_index(build_dir)
    return [path_inside(build_dir, s.get("file"), f"{build_dir / INDEX_NAME}: shard {k}")
            for k, s in enumerate(index["shards"])]


def read_pairs(build_dir: str | Path, columns: Iterable[str] | None = None) -> pa.Table:
    """Every row of a build (the shards its index lists, in order) as one Arrow table."""
    build_dir = Path(build_dir)
    paths = shard_paths(build_dir)
    tables = []
    for p in paths:
        if not p.is_file():
            raise ParaDriveError(f"{p} is listed in {build_dir / INDEX_NAME} but missing; "
                                 f"re-run the manifest stage (paradrive build --stages manifest "
                                 f"--force)")
        tables.append(pq.read_table(p, columns=list(columns) if columns else None))
    return pa.concat_tables(tables) if tables else SCHEMA.empty_table()


# --------------------------------------------------------------------------- publish

def publish(build_dir: str | Path, rows: list[dict], media: list[MediaFile], *,
            scenes: list[dict], skipped: list[dict], params: dict, fingerprint: str = "",
            build: str | None = None, log=None, selection: dict | None = None) -> dict:
    """Write shards, media and index under ``build_dir`` as one published build; returns the index.

    ``selection`` ({exclude_splits, excluded_scenes}) records which split files left which
    scenes out of the build."""
    build_dir = Path(build_dir)
    build_dir.mkdir(parents=True, exist_ok=True)
    for stale in build_dir.glob(f"{STAGING_PREFIX}*"):
        shutil.rmtree(stale, ignore_errors=True)
    table = rows_to_table(rows)
    ids = table.column("pair_id").to_pylist()
    if len(set(ids)) != len(ids):
        raise ParaDriveError("two scenes give the same pair id; scene ids must be unique")
    shards = split_rows(table, int(params.get("shard_rows") or 4096), params.get("shard_bytes"))
    compression = params.get("compression") or "zstd"
    staging = temporary_name(build_dir / STAGING_PREFIX)
    staging.mkdir()
    try:
        entries = []
        for i, shard in enumerate(shards):
            name = SHARD_PATTERN.format(i)
            pq.write_table(shard, staging / name,
                           compression=None if compression == "none" else compression,
                           row_group_size=max(1, int(params.get("row_group_rows") or 64)))
            entries.append({"file": name, "rows": shard.num_rows,
                            "bytes": (staging / name).stat().st_size,
                            "sha256": sha256_file(staging / name),
                            "first_pair_id": shard.column("pair_id")[0].as_py() if shard.num_rows else None,
                            "last_pair_id": shard.column("pair_id")[-1].as_py() if shard.num_rows else None})
        mode = params.get("media") or "hardlink"
        placed: dict[str, int] = {}
        for m in media:
            if m.src.resolve() == (build_dir / m.uri).resolve():  # written in place (truth views)
                placed["kept"] = placed.get("kept", 0) + 1
                continue
            done = place_file(m.src, build_dir / m.uri, mode, m.sha256)
            placed[done] = placed.get(done, 0) + 1
        index = {
            "format": "paradrive-pairs", "schema_version": SCHEMA_VERSION,
            "build": build or build_dir.name,
            "kind": params.get("kind") or "training",
            "created_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "software": {"paradrive": paradrive.__version__, "pyarrow": pa.__version__},
            "config_fingerprint": fingerprint,
            "params": params,
            "sort": ["pair_id"],
            "columns": [{"name": f.name, "type": str(f.type)} for f in SCHEMA],
            "shards": entries,
            "totals": {"rows": table.num_rows, "shards": len(entries),
                       "shard_bytes": sum(e["bytes"] for e in entries),
                       "media_files": len(media), "media_bytes": sum(m.bytes for m in media),
                       "scenes": len(scenes), "scenes_skipped": len(skipped)},
            "media": {"mode": mode, "placed": placed},
            "scenes": scenes,
            "skipped_scenes": skipped,
            **(selection or {"exclude_splits": [], "excluded_scenes": []}),
        }
        write_json(staging / INDEX_NAME, index)
        # Commit: withdraw the old index, swap the shards, then the new index lands last.
        (build_dir / INDEX_NAME).unlink(missing_ok=True)
        for e in entries:
            os.replace(staging / e["file"], build_dir / e["file"])
        keep = {e["file"] for e in entries}
        for old in build_dir.glob("pairs-*.parquet"):
            if old.name not in keep:
                old.unlink()
        os.replace(staging / INDEX_NAME, build_dir / INDEX_NAME)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    removed = _prune_media(build_dir, {m.uri for m in media})
    if log is not None:
        log.info("manifest: %d rows in %d shards, %d media files (%s), %d stale removed",
                 table.num_rows, len(entries), len(media), placed, removed)
    return index


def _prune_media(build_dir: Path, keep: set[str]) -> int:
    """Remove media files no row references any more (scenes dropped from the build)."""
    root = build_dir / MEDIA_DIR
    if not root.is_dir():
        return 0
    removed = 0
    for p in sorted(root.rglob("*"), reverse=True):
        rel = p.relative_to(build_dir).as_posix()
        if p.is_symlink() or p.is_file():
            if rel not in keep:
                p.unlink()
                removed += 1
        elif p.is_dir() and not any(p.iterdir()):
            p.rmdir()
    return removed


def build_manifest(build_dir: str | Path, scene_dirs: list[dict], params: dict, *,
                   fingerprint: str = "", build: str | None = None, log=None,
                   selection: dict | None = None) -> dict:
    """Rows from every scene in ``scene_dirs`` ([{scene_id, scene_uri, scene_dir}]) published
    under ``build_dir``. A scene whose clips cannot be used is skipped with its reason; no usable
    scene at all is an error."""
    rows: list[dict] = []
    media: list[MediaFile] = []
    scenes, skipped = [], []
    inference = params.get("kind") == "inference"
    for entry in sorted(scene_dirs, key=lambda s: s["scene_id"]):
        try:
            truth = None
            if inference:
                from paradrive.inference import truth_renderer

                truth = truth_renderer(entry["scene_dir"], build_dir, read_clips(entry["scene_dir"]))
            scene_rows_, scene_media, summary = scene_rows(
                entry["scene_dir"], verify_inputs=bool(params.get("verify_inputs", True)),
                quality=bool(params.get("quality", True)), truth=truth)
        except SceneError as exc:
            skipped.append({"scene_id": entry["scene_id"], "scene_uri": entry.get("scene_uri", ""),
                            "reason": str(exc)})
            if log is not None:
                log.warning("manifest: skipped %s", exc)
            continue
        summary["scene_uri"] = entry.get("scene_uri") or summary["scene_uri"]
        summary["scene_dir"] = entry.get("scene_location") or summary["scene_dir"]  # a URL root's own
        rows.extend(scene_rows_)
        media.extend(scene_media)
        scenes.append(summary)
    if not rows:
        reasons = "; ".join(s["reason"] for s in skipped) or "no scenes given"
        raise ParaDriveError(f"build {build or Path(build_dir).name}: no usable scene, nothing "
                             f"published ({reasons})")
    return publish(build_dir, rows, media, scenes=scenes, skipped=skipped, params=params,
                   fingerprint=fingerprint, build=build, log=log, selection=selection)


def run_stage(ctx) -> dict:
    """Stage entry (``stages/manifest.yaml``): called with a BuildContext."""
    params = dict(ctx.params)
    selection = params.pop("selection", None)
    index = build_manifest(ctx.build_dir, ctx.scenes, params, fingerprint=ctx.fingerprint,
                           build=ctx.build, log=ctx.log, selection=selection)
    return {"rows": index["totals"]["rows"], "shards": index["totals"]["shards"],
            "scenes": index["totals"]["scenes"], "skipped": [s["scene_id"] for s in index["skipped_scenes"]]}


__all__ = ["SCHEMA", "SCHEMA_VERSION", "COLUMNS", "build_manifest", "make_pair_id",
           "offset_token", "publish", "read_clips", "read_index", "read_pairs", "run_stage",
           "scene_rows", "shard_paths", "place_file"]
