"""Encoding a published build into its latent cache (:mod:`paradrive.latents`): what the
``encode`` stage and ``paradrive encode`` both run.

Every pair's target, source and condition videos are decoded (frames 0..F-1 at the encode size,
exactly as the adapter decodes them), encoded by Wan2.1's VAE (:func:`paradrive.wan.vae.encode_video`)
and stored in the storage dtype; each distinct video of a shard is decoded and encoded once. The
text embedding of the empty prompt is computed once. Shards land one at a time and are skipped
when a later run finds them, so a killed encode resumes at the shard it was writing.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import torch

import paradrive
from paradrive.data import frame_array, output_geometry, plane_sink, recammaster_camera
from paradrive.devices import resolve_device
from paradrive.errors import ConfigError, ParaDriveError
from paradrive.io import remove_stale_temporaries, sha256_file, write_json
from paradrive.io import stop_point
from paradrive.pairs import build_file, read_index, read_pairs
from paradrive.contracts.records import IndexRecord
from paradrive.video import each_frame
from paradrive import latents as cache
from paradrive.wan.recam import tiny_transformer_config
from paradrive.wan.text import EMBEDDING_FORM, empty_prompt_embedding, text_encoder_folders, tiny_text_embedding
from paradrive.wan.vae import (LATENT_CONVENTION, TEMPORAL_FACTOR, TINY, TINY_SEED, encode_video, folder_checksum,
                               latent_frames, latent_shape, load_vae, vae_checksum)

__all__ = ["EncodeSettings", "encode_build"]

_COLUMNS = ("pair_id", "num_frames", "width", "height", "offset_m", "condition_iteration", "rel_pose",
            "target_c2w", *(f"{role}_{k}" for role in cache.LATENT_ROLES for k in ("uri", "sha256")))
_COMPUTE_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}


@dataclass(frozen=True)
class EncodeSettings:
    """What an encode runs with (the ``encode`` stage's parameters; ``stages/encode.yaml`` says
    what each may be)."""

    vae: str | None
    text_encoder: str | None
    device: str
    dtype: str
    compute_dtype: str
    batch: int
    shard_pairs: int
    num_frames: int | None
    size: tuple[int, int] | None
    resize: str


@dataclass(frozen=True)
class _Plan:
    """The frames and size every pair is encoded at, and the key of everything else a shard's
    bytes depend on."""

    frames: int
    size: tuple[int, int]
    settings_key: str


def _vae_path(settings: EncodeSettings) -> str:
    if settings.vae is None:
        raise ConfigError("encode.vae is not set: the encode stage needs a local folder holding "
                          "Wan2.1's VAE in diffusers' layout; pass --set encode.vae=DIR (or "
                          "`paradrive encode BUILD --vae DIR`)")
    return settings.vae


def _text_path(settings: EncodeSettings) -> str:
    """The text encoder's folder: ``text_encoder``, else the VAE's when it is a whole Wan folder."""
    path = settings.text_encoder or _vae_path(settings)
    if path == TINY:
        return path
    if settings.text_encoder is None and not (Path(path) / "text_encoder").is_dir():
        raise ConfigError(f"encode.text_encoder is not set and the VAE folder {path} holds no "
                          f"text_encoder/: pass --set encode.text_encoder=DIR (a Wan2.1 diffusers "
                          f"folder with text_encoder/ and tokenizer/)")
    return path


def _frames(settings: EncodeSettings, clip_frames: list[int]) -> int:
    """Frames encoded per video: ``num_frames``, else the most of the form 4k + 1 every clip has."""
    shortest = min(clip_frames)
    if settings.num_frames is None:
        return 1 + (shortest - 1) // TEMPORAL_FACTOR * TEMPORAL_FACTOR
    if (settings.num_frames - 1) % TEMPORAL_FACTOR:
        raise ConfigError(f"encode.num_frames = {settings.num_frames} is not 4k + 1 (the VAE encodes "
                          f"the first frame alone, then groups of 4): use e.g. 121, 81 or null")
    if settings.num_frames > shortest:
        raise ConfigError(f"encode.num_frames = {settings.num_frames}, but the build has clips of "
                          f"{shortest} frames: lower it or set it to null")
    return settings.num_frames


def _size(settings: EncodeSettings, widths: set[int], heights: set[int]) -> tuple[int, int]:
    if settings.size is not None:
        if len(settings.size) != 2:
            raise ConfigError(f"encode.size = {list(settings.size)} must be [height, width], e.g. [480, 832]")
        height, width = settings.size
    elif len(widths) == 1 and len(heights) == 1:
        height, width = heights.pop(), widths.pop()
    else:
        raise ConfigError("the build's clips have several sizes: set encode.size=[H, W] "
                          "(multiples of 8, e.g. [480, 832])")
    if height % 8 or width % 8:
        raise ConfigError(f"encode size {height}x{width} is not a multiple of 8 (the VAE's spatial "
                          f"factor): set encode.size=[H, W], e.g. [480, 832]")
    return int(height), int(width)


def _digest(doc: Any) -> str:
    return hashlib.sha256(json.dumps(doc, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _shard_key(plan: _Plan, rows: pa.Table) -> str:
    """sha256 of what a shard's bytes depend on: the settings and each pair's id, videos and poses."""
    digest = hashlib.sha256(plan.settings_key.encode())
    for name in ("pair_id", *(f"{role}_sha256" for role in cache.LATENT_ROLES)):
        digest.update(json.dumps(rows.column(name).to_pylist()).encode())
    for name in ("rel_pose", "target_c2w"):
        digest.update(np.asarray(rows.column(name).to_pylist(), dtype=np.float64).tobytes())
    return digest.hexdigest()


class _Encoder:
    """The VAE, loaded on first use (a resumed encode whose shards all exist never loads it), and
    the decoding of one build's videos at the plan's frames and size."""

    def __init__(self, settings: EncodeSettings, build_dir: Path, index: IndexRecord, plan: _Plan):
        self.settings, self.build_dir, self.index, self.plan = settings, build_dir, index, plan
        self.device = resolve_device(settings.device)
        self._vae: Any = None

    @property
    def vae(self) -> Any:
        if self._vae is None:
            self._vae = load_vae(_vae_path(self.settings), self.device,
                                 _COMPUTE_DTYPES[self.settings.compute_dtype])
        return self._vae

    def decode(self, uri: str, width: int, height: int, pair_id: str) -> torch.Tensor:
        """Frames 0..F-1 of a video as float32 (3, F, H, W) in [-1, 1] on the CPU, decoded as
        ``PairDataset`` decodes them (planar RGB, area resize, centre crop, x / 127.5 - 1)."""
        geo = output_geometry(width, height, self.plan.size, self.settings.resize)
        path = build_file(self.build_dir, uri, f"{self.build_dir}: row {pair_id}", self.index)
        out = torch.empty((3, self.plan.frames, *geo["size"]), dtype=torch.float32, device="cpu")
        array = frame_array(out)
        each_frame(path, list(range(self.plan.frames)), plane_sink(lambda idx: array[:, idx], geo, torch.float32),
                   size=geo["resize"], planar=True)
        return out

    def encode(self, videos: list[torch.Tensor]) -> torch.Tensor:
        """(V, 16, T', h, w) in the storage dtype, ``batch`` videos per VAE call."""
        out = []
        for start in range(0, len(videos), self.settings.batch):
            chunk = torch.stack(videos[start:start + self.settings.batch]).to(self.device)
            out.append(encode_video(self.vae, chunk).to(cache.STORAGE_DTYPES[self.settings.dtype]).cpu())
        return torch.cat(out)


def _shard_tensors(encoder: _Encoder, rows: pa.Table) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """latents, pair_videos, rel_pose and camera of one shard's rows."""
    plan = encoder.plan
    cols = rows.to_pydict()
    slots: dict[str, int] = {}
    videos: list[torch.Tensor] = []
    pair_videos = torch.full((rows.num_rows, 3), -1, dtype=torch.int64, device="cpu")
    for i, pair_id in enumerate(cols["pair_id"]):
        for j, role in enumerate(cache.LATENT_ROLES):
            uri, sha = cols[f"{role}_uri"][i], cols[f"{role}_sha256"][i]
            if uri is None:
                continue
            if sha not in slots:
                slots[sha] = len(videos)
                videos.append(encoder.decode(uri, cols["width"][i], cols["height"][i], pair_id))
            pair_videos[i, j] = slots[sha]
    steps = np.arange(latent_frames(plan.frames)) * TEMPORAL_FACTOR
    rel, camera = [], []
    for i in range(rows.num_rows):
        rel_pose = np.asarray(cols["rel_pose"][i], dtype=np.float64).reshape(-1, 4, 4)[:plan.frames]
        target_c2w = np.asarray(cols["target_c2w"][i], dtype=np.float64).reshape(-1, 4, 4)[:plan.frames]
        rel.append(rel_pose[steps, :3, :4].reshape(-1, 12))
        camera.append(recammaster_camera(target_c2w, target_c2w @ rel_pose))
    return (encoder.encode(videos), pair_videos,
            torch.from_numpy(np.stack(rel).astype(np.float32)), torch.from_numpy(np.stack(camera)))


def _shards(rows: pa.Table, shard_pairs: int) -> Iterator[pa.Table]:
    for start in range(0, rows.num_rows, shard_pairs):
        yield rows.slice(start, shard_pairs)


def _text(settings: EncodeSettings, folder: Path, device: torch.device, log: logging.Logger) -> dict:
    """The text embedding's file (written unless this encoder's is there) and its record."""
    path = _text_path(settings)
    if path == TINY:   # the tiny transformer's stand-in for umT5, as `train --config smoke` draws it
        tiny = tiny_text_embedding(TINY_SEED, int(tiny_transformer_config()["text_dim"]))
        sums = {"encoder_sha256": hashlib.sha256(tiny.numpy().tobytes()).hexdigest(), "tokenizer_sha256": TINY}
    else:
        encoder_dir, tokenizer_dir = text_encoder_folders(path)
        sums = {"encoder_sha256": folder_checksum(encoder_dir), "tokenizer_sha256": folder_checksum(tokenizer_dir)}
    rel = f"text/empty-prompt-{_digest(sums)[:12]}.safetensors"
    target = folder / rel
    if not target.is_file():
        log.info("encode: text embedding of the empty prompt from %s", path)
        written = cache.write_text_embedding(target, tiny if path == TINY else empty_prompt_embedding(
            path, device, _COMPUTE_DTYPES[settings.compute_dtype]))
    else:
        written = {"bytes": target.stat().st_size, "sha256": sha256_file(target)}
    from safetensors import safe_open

    with safe_open(str(target), framework="pt") as handle:
        shape = list(handle.get_slice("text_embedding").get_shape())
    return {"file": rel, **written, "shape": shape, "path": path, **sums, "form": EMBEDDING_FORM}


def _remove_unlisted(folder: Path, keep: set[str]) -> None:
    """Files of an earlier cache that the new index does not name (after the switch)."""
    for sub in ("shards", "text"):
        for path in sorted((folder / sub).glob("*")) if (folder / sub).is_dir() else []:
            if f"{sub}/{path.name}" not in keep:
                if path.is_dir():
                    shutil.rmtree(path, ignore_errors=True)
                else:
                    path.unlink(missing_ok=True)


def _plan(settings: EncodeSettings, rows: pa.Table, vae_sha256: str) -> _Plan:
    frames = _frames(settings, rows.column("num_frames").to_pylist())
    size = _size(settings, set(rows.column("width").to_pylist()), set(rows.column("height").to_pylist()))
    key = _digest({"vae": vae_sha256, "frames": frames, "size": size, "resize": settings.resize,
                   "dtype": settings.dtype, "compute_dtype": settings.compute_dtype,
                   "convention": LATENT_CONVENTION, "schema": cache.LATENTS_SCHEMA_VERSION})
    return _Plan(frames=frames, size=size, settings_key=key)


def encode_build(build_dir: str | Path, settings: EncodeSettings, *, log: logging.Logger | None = None,
                 fingerprint: str = "", progress: Callable[[int, int], None] | None = None) -> dict:
    """Encode the build's pairs into ``<build>/latents/`` and publish its index; returns the
    index document. Shards already there (a killed or earlier run) are kept, not encoded again."""
    log = log or logging.getLogger("paradrive.encode")
    build_dir = Path(build_dir)
    index = read_index(build_dir)
    vae_sha256 = vae_checksum(_vae_path(settings))
    # the rows of the version it read, each shard checked against its sha256 in the index
    rows = read_pairs(build_dir, _COLUMNS, index, verify=True)
    if rows.num_rows == 0:
        raise ParaDriveError(f"build {index.build} has no pairs to encode ({build_dir})")
    plan = _plan(settings, rows, vae_sha256)
    folder = cache.latents_dir(build_dir)
    what = f"{plan.frames} frames of {plan.size[0]}x{plan.size[1]}, {settings.dtype}"
    with cache.writer_lock(build_dir, what):   # a second encode of this build is refused here
        remove_stale_temporaries(folder)
        encoder = _Encoder(settings, build_dir, index, plan)
        text = _text(settings, folder, encoder.device, log)
        entries, total = [], -(-rows.num_rows // settings.shard_pairs)
        for k, shard in enumerate(_shards(rows, settings.shard_pairs)):
            entries.append(_encode_shard(encoder, shard, folder, log))
            stop_point(f"encode:shard-{k}")
            if progress is not None:
                progress(k + 1, total)
        doc = _index_doc(index, settings, plan, vae_sha256, text, entries, fingerprint)
        _check_listed(folder, [*entries, text])
        write_json(cache.latents_index_path(build_dir), doc)
        _remove_unlisted(folder, {e["file"] for e in entries} | {text["file"]})
    log.info("encode: %d pairs, %d videos in %d shards (%.1f MB)", doc["totals"]["pairs"],
             doc["totals"]["videos"], len(entries), doc["totals"]["bytes"] / 1e6)
    return doc


def _check_listed(folder: Path, entries: list[dict]) -> None:
    """Every file the new index lists is there at its size, checked before the index is
    written: an index never names a shard that does not exist."""
    for entry in entries:
        path = folder / entry["file"]
        size = path.stat().st_size if path.is_file() else None
        if size != entry["bytes"]:
            state = "is missing" if size is None else f"has {size} bytes, not {entry['bytes']}"
            raise ParaDriveError(f"{path} {state} after this encode wrote it (removed or changed by "
                                 f"another process); the index was not written: run the encode again")


def _encode_shard(encoder: _Encoder, shard: pa.Table, folder: Path, log: logging.Logger) -> dict:
    """One shard's index entry; encoded and written unless a file of the same key is there."""
    from safetensors import safe_open

    rel = f"shards/{_shard_key(encoder.plan, shard)}.safetensors"
    path = folder / rel
    ids = shard.column("pair_id").to_pylist()
    if path.is_file():
        written = {"bytes": path.stat().st_size, "sha256": sha256_file(path)}
    else:
        t0 = time.time()
        latents, pair_videos, rel_pose, camera = _shard_tensors(encoder, shard)
        written = cache.write_shard(path, ids, latents, pair_videos, rel_pose, camera)
        log.info("encode: %s (%d pairs, %d videos) in %.1f s", rel, len(ids), latents.shape[0], time.time() - t0)
    with safe_open(str(path), framework="pt") as handle:
        videos = handle.get_slice("latents").get_shape()[0]
    return {"file": rel, "pairs": len(ids), "videos": videos, "first_pair_id": ids[0],
            "last_pair_id": ids[-1], **written}


def _index_doc(index: IndexRecord, settings: EncodeSettings, plan: _Plan, vae_sha256: str, text: dict,
               entries: list[dict], fingerprint: str) -> dict:
    return {
        "format": cache.LATENTS_FORMAT, "schema_version": cache.LATENTS_SCHEMA_VERSION,
        "build": index.build, "created_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "software": {"paradrive": paradrive.__version__, "torch": torch.__version__},
        "fingerprint": fingerprint, "settings": asdict(settings),
        "pairs": {"version": index.version, "rows": index.totals.rows, "shards_sha256": cache.pairs_binding(index)},
        "vae": {"path": _vae_path(settings), "sha256": vae_sha256},
        "convention": LATENT_CONVENTION, "dtype": settings.dtype, "compute_dtype": settings.compute_dtype,
        "num_frames": plan.frames, "latent_frames": latent_frames(plan.frames),
        "frame_of_latent": [TEMPORAL_FACTOR * k for k in range(latent_frames(plan.frames))],
        "size": list(plan.size), "resize": settings.resize,
        "latent_shape": list(latent_shape(plan.frames, *plan.size)),
        "camera": {"rel_pose": "per latent frame k: the top 3x4 rows of rel_pose (T_target<-source) at "
                               "clip frame 4k, row-major",
                   "camera": "ReCamMaster's camera condition: the target camera at clip frame 4k in the "
                             "source camera's coordinates at frame 0, top 3x4 rows, row-major"},
        "text": text, "shards": entries,
        "totals": {"pairs": sum(e["pairs"] for e in entries), "videos": sum(e["videos"] for e in entries),
                   "bytes": sum(e["bytes"] for e in entries) + text["bytes"]},
    }
