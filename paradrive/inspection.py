"""What a data engineer asks of a published build (``paradrive inspect BUILD`` prints it,
:mod:`paradrive.commands.inspect`).

Counts by dataset / scene / camera / clip / offset / checkpoint, per-scene quality, checksum
verification of the shards and every referenced video (``--verify``), a machine-readable summary
(``--json``) and pictures (``--sheet out.png``: a contact sheet of a few pairs, ``out_trajectories.png``: the recorded
and shifted trajectories seen from above, and ``out_rig.png``: the rig and its shifted cameras
in 3D; :mod:`paradrive.trajectories`).
"""

from __future__ import annotations

import os
from collections import Counter, defaultdict, deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from paradrive.contracts.records import IndexRecord
from paradrive.errors import ParaDriveError
from paradrive.io import PathEscapeError, atomic_path, sha256_file
from paradrive.pairs import build_file, iter_shard, read_index, read_pairs, shard_paths
from paradrive.streams import format_offset, stream_transform
from paradrive.trajectories import rig_picture, trajectories_picture

__all__ = ["summarize", "verify_build", "default_jobs", "contact_sheet", "trajectories_picture", "rig_picture"]

ROLES = ("source", "condition", "target")
T = TypeVar("T")
_SUMMARY_COLUMNS = ["pair_id", "dataset", "scene_id", "camera", "clip", "offset_m",
                    "condition_iteration", "source_iteration", "condition_psnr",
                    "condition_ssim", "fit_train_psnr", "fit_train_ssim"]


# --------------------------------------------------------------------------- summary

def _mean(values) -> float | None:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return round(float(np.mean(vals)), 4) if vals else None


def summarize(build_dir: str | Path, index: IndexRecord | None = None) -> dict:
    """Counts and quality figures of a build (of the version ``index`` names; default: the
    current one), as plain JSON-able data."""
    build_dir = Path(build_dir)
    index = index or read_index(build_dir)
    cols = read_pairs(build_dir, _SUMMARY_COLUMNS, index).to_pydict()
    n = len(cols["pair_id"])

    def count(key, fmt=str):
        c = Counter(fmt(v) for v in cols[key])
        return dict(sorted(c.items()))

    offsets = Counter(cols["offset_m"])
    counts = {
        "dataset": count("dataset"),
        "scene": count("scene_id"),
        "camera": count("camera"),
        "clip": count("clip"),
        "offset": {format_offset(d): offsets[d] for d in sorted(offsets)},
        "checkpoint": count("condition_iteration", lambda v: f"{int(v):06d}"),
    }
    by_scene: dict[str, dict] = defaultdict(lambda: defaultdict(lambda: ([], [])))
    fit: dict[str, tuple] = {}
    for i in range(n):
        sid, it = cols["scene_id"][i], f"{int(cols['condition_iteration'][i]):06d}"
        by_scene[sid][it][0].append(cols["condition_psnr"][i])
        by_scene[sid][it][1].append(cols["condition_ssim"][i])
        fit[sid] = (cols["fit_train_psnr"][i], cols["fit_train_ssim"][i])
    held = {s.scene_id: s for s in index.scenes}
    quality = {sid: {"fit_train_psnr": fit[sid][0], "fit_train_ssim": fit[sid][1],
                     "heldout_psnr": held[sid].heldout_psnr if sid in held else None,
                     "heldout_ssim": held[sid].heldout_ssim if sid in held else None,
                     "condition": {it: {"psnr": _mean(p), "ssim": _mean(s)}
                                   for it, (p, s) in sorted(cps.items())}}
               for sid, cps in sorted(by_scene.items())}
    overall: defaultdict[str, tuple[list, list]] = defaultdict(lambda: ([], []))
    for i in range(n):
        it = f"{int(cols['condition_iteration'][i]):06d}"
        overall[it][0].append(cols["condition_psnr"][i])
        overall[it][1].append(cols["condition_ssim"][i])
    return {
        "build": str(build_dir), "name": index.build, "rows": n,
        "shards": len(index.shards), "config_fingerprint": index.config_fingerprint,
        "software": index.software, "created_at": index.created_at,
        "totals": index.totals.model_dump(), "counts": counts,
        "quality": {"by_checkpoint": {it: {"psnr": _mean(p), "ssim": _mean(s)}
                                      for it, (p, s) in sorted(overall.items())},
                    "scenes": quality},
        "skipped_scenes": [s.model_dump() for s in index.skipped_scenes],
        "kind": index.kind,
        "transform": sorted({s.transform for s in index.scenes}),
        "exclude_splits": [s.model_dump() for s in index.exclude_splits],
        "excluded_scenes": [s.model_dump() for s in index.excluded_scenes],
        "heldout_filter": index.heldout_filter.model_dump() if index.heldout_filter else None,
    }


# --------------------------------------------------------------------------- verify

# A plain re-run re-hashes the clips and redoes what changed, then publishes again.
HEAL = "re-run the build without --stages (the same paradrive build command): it redoes what is damaged"


def _check_file(path: Path, size: int | None, sha: str | None, what: str) -> str | None:
    if not path.is_file():
        return f"missing: {path} ({what}); {HEAL}"
    actual_size = path.stat().st_size
    if size is not None and actual_size != size:
        return (f"corrupt: {path} ({what}) has {actual_size} bytes, the manifest says {size}; "
                f"{HEAL}")
    if sha:
        actual = sha256_file(path)
        if actual != sha:
            return (f"corrupt: {path} ({what}) sha256 {actual[:12]}… differs from the manifest's "
                    f"{sha[:12]}…; {HEAL}")
    return None


def default_jobs() -> int:
    """Files hashed at once by ``verify_build``: hashing and reading release the GIL, so threads
    scale with the cores until the disk is the limit."""
    return min(8, os.cpu_count() or 2)


def verify_build(build_dir: str | Path, jobs: int | None = None,
                 index: IndexRecord | None = None) -> dict:
    """Re-hash every shard (against index.json) and every referenced video (against the rows).

    Returns {"ok", "checked_files", "problems": ["missing: <path> …" | "corrupt: <path> …" |
    "unsafe: <row> …"]}. A URI that leads out of the build is a problem and is never read.

    It streams: rows are read a batch at a time and at most a few files per job are in flight,
    so memory stays flat however many pairs the build has. ``jobs`` files are hashed at once
    (default :func:`default_jobs`); problems come in row order whatever ``jobs`` is. ``index``:
    the version to check (default: the one ``index.json`` names now).
    """
    build_dir = Path(build_dir)
    index = index or read_index(build_dir)
    jobs = jobs or default_jobs()
    shards = [(path, s.bytes, s.sha256, "shard")
              for path, s in zip(shard_paths(build_dir, index), index.shards)]
    problems = [p for p in _ordered(_check, shards, jobs) if p]
    if problems:  # rows cannot be trusted when a shard is bad
        return {"ok": False, "checked_files": len(shards), "problems": problems}
    media = _MediaChecks(build_dir, index)
    try:
        problems += [p for p in _ordered(_check, media.items(shards), jobs) if p]
    except ParaDriveError as exc:  # a shard whose checksum matches yet does not parse
        problems.append(str(exc))
    from paradrive.latents import verify_latents  # torch: only when verifying

    latents = verify_latents(build_dir)   # the Wan2.1 latent cache, when the build has one
    problems += latents["problems"]
    return {"ok": not problems, "checked_files": len(shards) + media.files + latents["checked_files"],
            "problems": problems}


_ROW_COLUMNS = ["pair_id", "scene_id"] + [f"{r}_{k}" for r in ROLES for k in ("uri", "sha256", "bytes")]


class _MediaChecks:
    """The videos the rows reference, each once, as checks in row order: (path, size, sha256,
    what) for a file, or the text of an 'unsafe' problem. Rows sort by pair_id, which starts
    with the scene id, and a video serves only rows of its own scene, so a video is known
    already only within the current scene: the set of those seen holds one scene's videos."""

    def __init__(self, build_dir: Path, index):
        self.build_dir, self.index = build_dir, index
        self.files = 0

    def items(self, shards: list[tuple]) -> Iterator[tuple | str]:
        scene, seen = None, set[str]()
        for path, *_ in shards:
            for batch in iter_shard(path, _ROW_COLUMNS):
                cols = batch.to_pydict()
                for i, pair_id in enumerate(cols["pair_id"]):
                    if cols["scene_id"][i] != scene:
                        scene, seen = cols["scene_id"][i], set()
                    for role in ROLES:
                        uri = cols[f"{role}_uri"][i]
                        if uri is None or uri in seen:  # an inference row of a real log: no true view
                            continue
                        seen.add(uri)
                        yield self._item(uri, cols[f"{role}_bytes"][i], cols[f"{role}_sha256"][i],
                                         f"{role} video", f"row {pair_id} column {role}_uri")

    def _item(self, uri: str, size: int | None, sha: str | None, what: str, where: str) -> tuple | str:
        try:
            path = build_file(self.build_dir, uri, f"{self.build_dir}: {where}", self.index)
        except PathEscapeError as exc:
            return f"unsafe: {exc}"
        self.files += 1
        return (path, size, sha, what)


def _check(item: tuple | str) -> str | None:
    return item if isinstance(item, str) else _check_file(*item)


def _ordered(fn: Callable[[Any], T], items: Iterable[Any], jobs: int) -> Iterator[T]:
    """``fn`` over ``items`` on ``jobs`` threads, results in the items' order, with at most
    ``4 * jobs`` items taken ahead (``Executor.map`` would take them all first)."""
    if jobs <= 1:
        yield from map(fn, items)
        return
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        pending: deque[Future[T]] = deque()
        for item in items:
            pending.append(pool.submit(fn, item))
            if len(pending) >= 4 * jobs:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


# --------------------------------------------------------------------------- pictures

def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType sizes
        return ImageFont.load_default()


def _pick_pairs(rows: list[dict], count: int) -> list[dict]:
    """A few pairs that show the range: one scene and clip, offsets spread, checkpoints cycled."""
    if not rows:
        return []
    sid = rows[0]["scene_id"]
    clips = sorted({r["clip"] for r in rows if r["scene_id"] == sid})
    clip = "middle" if "middle" in clips else clips[0]
    pool = [r for r in rows if r["scene_id"] == sid and r["clip"] == clip]
    offsets = sorted({r["offset_m"] for r in pool}, key=lambda d: (abs(d), -d))
    picks = [offsets[int(round(k))] for k in np.linspace(0, len(offsets) - 1, min(count, len(offsets)))]
    iterations = sorted({r["condition_iteration"] for r in pool})
    chosen: list[dict] = []
    for k, d in enumerate(picks):
        it = iterations[k % len(iterations)]
        chosen.extend(r for r in pool if r["offset_m"] == d and r["condition_iteration"] == it)
    return chosen[:count]


def sheet_labels(row: dict, kind: str) -> list[tuple[str, str, str]]:
    """(role, what it shows, its checkpoint) per video of a pair on the contact sheet; a
    longitudinal build's source is moved along the path, not shifted beside it."""
    streams = (row.get("source_stream") or "", row.get("condition_stream") or "")
    moved = any(stream_transform(name) == "longitudinal" for name in streams)
    shift = f"{'moved' if moved else 'shifted'} {format_offset(row['offset_m'])}"
    if kind == "inference":
        return [("source", "recorded camera", ""),
                ("condition", shift, f"ckpt {row['condition_iteration']}"),
                ("target", f"true view, {shift}", "")]
    return [("source", shift, f"ckpt {row['source_iteration']}"),
            ("condition", "recorded path", f"ckpt {row['condition_iteration']}"),
            ("target", "recorded camera", "")]


def contact_sheet(build_dir: str | Path, out: str | Path, *, pairs: int = 3, frames: int = 3,
                  thumb_width: int = 208, index: IndexRecord | None = None) -> Path:
    """A PNG with ``pairs`` pairs: source / condition / target thumbnails at ``frames`` frames."""
    from PIL import Image, ImageDraw

    from paradrive.video import decode_frames

    build_dir, out = Path(build_dir), Path(out)
    index = index or read_index(build_dir)
    cols = read_pairs(build_dir, ["pair_id", "scene_id", "clip", "offset_m", "condition_iteration",
                                  "source_iteration", "num_frames", "width", "height",
                                  "source_uri", "condition_uri", "target_uri", "condition_psnr",
                                  "condition_ssim", "frame_indices"], index).to_pylist()
    chosen = _pick_pairs(cols, pairs)
    if not chosen:
        raise ParaDriveError(f"{build_dir}: the build has no pairs to draw")
    w0, h0 = chosen[0]["width"], chosen[0]["height"]
    tw = thumb_width
    th = max(2, int(round(tw * h0 / w0)) // 2 * 2)
    label_w, pad, head = 190, 6, 26
    font, small = _font(15), _font(12)
    block_h = head + 3 * (th + pad)
    sheet_w = label_w + frames * (tw + pad) + pad
    sheet_h = pad + 18 + len(chosen) * (block_h + pad)
    sheet = Image.new("RGB", (sheet_w, sheet_h), (250, 250, 250))
    draw = ImageDraw.Draw(sheet)
    y = pad
    draw.text((pad, y), f"{build_dir.name}: {len(chosen)} pairs", fill=(0, 0, 0), font=font)
    y += 18
    for row in chosen:
        n = int(row["num_frames"])
        picks = sorted({int(round(x)) for x in np.linspace(0, n - 1, min(frames, n))})
        psnr = row["condition_psnr"]
        draw.rectangle([0, y, sheet_w, y + head - 4], fill=(225, 232, 242))
        draw.text((pad, y + 4), f"{row['pair_id']}    offset {format_offset(row['offset_m'])}    "
                                f"condition PSNR {psnr:.1f} dB" if psnr is not None else
                                row["pair_id"], fill=(0, 0, 0), font=font)
        y += head
        for (role, line2, line3) in sheet_labels(row, index.kind):
            if row[f"{role}_uri"] is None:  # an inference row of a real log: no true view
                continue
            video = build_file(build_dir, row[f"{role}_uri"],
                               f"{build_dir}: row {row['pair_id']} column {role}_uri", index)
            pixels = decode_frames(video, picks, size=(th, tw))
            draw.text((pad, y + 4), role, fill=(0, 0, 0), font=font)
            draw.text((pad, y + 24), line2, fill=(70, 70, 70), font=small)
            draw.text((pad, y + 40), line3, fill=(70, 70, 70), font=small)
            for k, (p, img) in enumerate(zip(picks, pixels)):
                x = label_w + k * (tw + pad)
                sheet.paste(Image.fromarray(img), (x, y))
                frame_no = row["frame_indices"][p] if row["frame_indices"] else p
                draw.text((x + 4, y + 3), f"f{frame_no}", fill=(255, 255, 0), font=small,
                          stroke_width=2, stroke_fill=(0, 0, 0))
            y += th + pad
        y += pad
    with atomic_path(out) as tmp:
        sheet.save(tmp, format="PNG")
    return out
