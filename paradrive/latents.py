"""The latent cache of a build: Wan2.1 VAE latents of every pair's videos, the per-latent-frame
camera inputs and the empty-prompt text embedding, beside the pairs they were encoded from.

Layout (under ``<manifests>/<build>/``)::

    latents/index.json                       the pointer readers follow (switched by rename)
    latents/shards/<key>.safetensors         one shard per run of ``shard_pairs`` pairs in pair_id order
    latents/text/empty-prompt-<sha12>.safetensors   umT5(""), (512, D) float32

A shard is a safetensors file holding

    latents      (V, 16, T', H/8, W/8) in the storage dtype (bfloat16 by default): the normalised
                 posterior mean of each *distinct* video the shard's pairs use, once
    pair_videos  (N, 3) int64: the row of ``latents`` of each pair's target, source and condition
                 (-1: an inference row without a target)
    rel_pose     (N, T', 12) float32: per latent frame k, the top 3x4 rows of the pair's rel_pose
                 (T_target<-source) at clip frame 4k, row-major
    camera       (N, T', 12) float32: ReCamMaster's camera condition (``paradrive.data.recammaster_camera``)

and, in its metadata, the pair ids in order. Why safetensors and not Parquet: bfloat16 is a
native type (Arrow has none); the header gives every tensor's byte range, so a map-style
dataset reads one pair's three latents by slicing a memory map (random access without reading
the shard); and it is the format diffusers' own weights use, so every Wan trainer reads it.
Distinct videos are stored once per shard because pairs share them (a clip's target serves every
offset and checkpoint, a source every checkpoint): a shard of a clip's pairs holds far fewer
videos than three per pair.

Shards are named by a key over everything their bytes depend on (the pairs' ids, their videos'
sha256, their poses, the VAE's folder checksum, frames, size and dtypes), so a killed encode
finds the shards it finished and a re-encode of an unchanged build writes nothing. The index is
written last and by rename: a reader sees the previous cache or the new one, never a mix, and it
is bound to the exact pair shards it was made from (their sha256, in order), so a build
republished with other rows is never read with stale latents.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import socket
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from paradrive.errors import ConfigError, ParaDriveError
from paradrive.io import atomic_path, path_inside, sha256_file
from paradrive.pairs import read_index
from paradrive.contracts.records import IndexRecord

__all__ = ["LATENTS_DIR", "LATENTS_FORMAT", "LATENTS_SCHEMA_VERSION", "LATENT_ROLES", "STORAGE_DTYPES",
           "latents_dir", "latents_index_path", "read_latents_index", "has_latents", "write_shard",
           "write_text_embedding", "LatentReader", "collate_latents", "verify_latents", "latents_summary"]

LATENTS_DIR = "latents"
LATENTS_FORMAT = "paradrive-latents"
LATENTS_SCHEMA_VERSION = 1
LATENT_ROLES = ("target", "source", "condition")   # the columns of pair_videos
STORAGE_DTYPES = {"bfloat16": torch.bfloat16, "float16": torch.float16, "float32": torch.float32}
_ENCODE_FIX = "run `paradrive encode BUILD --vae DIR` (or the build with --stages ...,encode)"


def latents_dir(build_dir: str | Path) -> Path:
    return Path(build_dir) / LATENTS_DIR


def latents_index_path(build_dir: str | Path) -> Path:
    return latents_dir(build_dir) / "index.json"


def has_latents(build_dir: str | Path) -> bool:
    return latents_index_path(build_dir).is_file()


def pairs_binding(index: IndexRecord) -> list[str]:
    """What a latent cache is bound to: the sha256 of the build's pair shards, in order."""
    return [s.sha256 for s in index.shards]


def read_latents_index(build_dir: str | Path, index: IndexRecord | None = None) -> dict:
    """``latents/index.json``, checked to belong to the pairs ``index.json`` publishes now;
    ParaDriveError naming the file and the fix otherwise."""
    path = latents_index_path(build_dir)
    index = index or read_index(build_dir)
    if not path.is_file():
        raise ParaDriveError(f"{path} is missing: build {index.build} has no latents; {_ENCODE_FIX}")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ParaDriveError(f"{path} is not valid JSON ({exc}); {_ENCODE_FIX} again") from exc
    if not isinstance(doc, dict) or doc.get("format") != LATENTS_FORMAT \
            or doc.get("schema_version") != LATENTS_SCHEMA_VERSION:
        raise ParaDriveError(f"{path} is not a paradrive latent index of schema "
                             f"{LATENTS_SCHEMA_VERSION}; {_ENCODE_FIX} again")
    if doc["pairs"]["shards_sha256"] != pairs_binding(index):
        raise ParaDriveError(f"{path} was encoded from other pairs than build {index.build} "
                             f"publishes now (version {doc['pairs'].get('version')}, now "
                             f"{index.version}); {_ENCODE_FIX} again")
    return doc


def _file(build_dir: str | Path, rel: object, what: str) -> Path:
    return path_inside(latents_dir(build_dir), rel, f"{latents_index_path(build_dir)}: {what}")


# --------------------------------------------------------------------------- writing

WRITER_LOCK = "writer.lock"


class CacheLocked(ConfigError):
    """Another encode writes this build's latent cache now."""


@contextlib.contextmanager
def writer_lock(build_dir: str | Path, what: str) -> Iterator[None]:
    """Hold ``<build>/latents/writer.lock`` while writing the cache: one writer at a time.

    Two encodes of one build (other settings, or the same twice) would each remove the other's
    shards as stale and publish an index naming files that are gone. The lock is an ``flock``,
    which the kernel drops when its holder dies (even by SIGKILL), so a re-run after a kill takes
    it at once; the holder's host, pid, start time and ``what`` (its settings) are written in it.
    A second encode does not wait: it raises :class:`CacheLocked` naming the holder.
    """
    folder = latents_dir(build_dir)
    path = folder / WRITER_LOCK
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:   # a read-only build folder (a published copy, a read-only mount)
        raise ConfigError(f"{folder}: the latent cache cannot be written there ({exc.strerror}); make "
                          f"the build folder writable, or encode a writable copy of it") from exc
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise CacheLocked(f"{folder} is being written by another encode ({_holder(path)}); wait for "
                              f"it to finish (or stop it), then run this encode again") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"host": socket.gethostname(), "pid": os.getpid(),
                                  "since": time.strftime("%Y-%m-%d %H:%M:%S"), "what": what}).encode(), 0)
        try:
            yield
        finally:
            os.ftruncate(fd, 0)
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)


def _holder(path: Path) -> str:
    """Who holds the writer lock at ``path``, as its record says."""
    try:
        doc = json.loads(path.read_text())
        return f"host {doc['host']}, pid {doc['pid']}, since {doc['since']}, {doc['what']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "its record is not written yet"


def write_shard(path: Path, pair_ids: Sequence[str], latents: torch.Tensor, pair_videos: torch.Tensor,
                rel_pose: torch.Tensor, camera: torch.Tensor) -> dict:
    """One shard (see the module docstring), landed by rename; returns its {bytes, sha256}."""
    from safetensors.torch import save

    tensors = {"latents": latents.contiguous().cpu(), "pair_videos": pair_videos.to(torch.int64).contiguous().cpu(),
               "rel_pose": rel_pose.float().contiguous().cpu(), "camera": camera.float().contiguous().cpu()}
    # one metadata key: safetensors writes several in an order that changes between processes
    return _write(path, save(tensors, metadata={"pair_ids": json.dumps(list(pair_ids))}))


def _write(path: Path, data: bytes) -> dict:
    """``data`` landed at ``path`` by rename (a reader never sees half a file); {bytes, sha256}."""
    with atomic_path(path, size=len(data)) as tmp:   # a full disk: how much more it needed
        tmp.write_bytes(data)
    return {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}


def write_text_embedding(path: Path, embedding: torch.Tensor) -> dict:
    """The (L, D) float32 text embedding as ``text_embedding`` in a safetensors file."""
    from safetensors.torch import save

    return _write(path, save({"text_embedding": embedding.float().contiguous().cpu()}))


# --------------------------------------------------------------------------- reading

def _widened(latents: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``latents`` as ``dtype``. The default pairing, bfloat16 stored and float32 asked for, is
    widened in numpy, bit for bit as torch does it but in one thread: a torch conversion this
    size spreads over the intra-op threads, which wait for a core on a busy machine, as the
    adapter's frames would (``paradrive.data``). Any other change of type is torch's."""
    if latents.dtype == dtype:
        return latents
    if dtype == torch.float32 and latents.dtype == torch.bfloat16:
        # a bfloat16 is the top half of the float32 it stands for
        bits = np.left_shift(latents.view(torch.int16).numpy().view(np.uint16), 16, dtype=np.uint32)
        return torch.from_numpy(bits.view(np.float32))
    return latents.to(dtype)


@dataclass
class _Shard:
    path: Path
    start: int          # global pair index of its first pair
    count: int


class LatentReader:
    """Per-pair latent samples of a build, for ``PairDataset(build, latents=True)``.

    Opened once with the pairs index the dataset read, so both come from one publication; each
    sample slices one shard's memory map (the shards are opened lazily, again after a fork).
    ``dtype``: the latents' type in a sample (float32 by default; the storage dtype costs no
    conversion).
    """

    def __init__(self, build_dir: str | Path, index: IndexRecord, pair_ids: Sequence[str],
                 dtype: torch.dtype = torch.float32):
        if not dtype.is_floating_point:
            raise ValueError(f"latents are floating point; dtype {dtype} cannot hold them "
                             f"(use float32, bfloat16 or float16)")
        self.build_dir, self.dtype = Path(build_dir), dtype
        self.doc = read_latents_index(build_dir, index)
        self.shards: list[_Shard] = []
        start = 0
        for k, entry in enumerate(self.doc["shards"]):
            path = _file(build_dir, entry["file"], f"shard {k}")
            ids = list(pair_ids[start:start + int(entry["pairs"])])
            if not ids or [ids[0], ids[-1]] != [entry["first_pair_id"], entry["last_pair_id"]]:
                raise ParaDriveError(f"{path}: its pairs are not the build's pairs "
                                     f"{start}..{start + entry['pairs'] - 1}; {_ENCODE_FIX} again")
            self.shards.append(_Shard(path, start, int(entry["pairs"])))
            start += int(entry["pairs"])
        if start != len(pair_ids):
            raise ParaDriveError(f"{latents_index_path(build_dir)} covers {start} pairs, the build has "
                                 f"{len(pair_ids)}; {_ENCODE_FIX} again")
        self._starts = np.array([s.start for s in self.shards], dtype=np.int64)
        self._text: torch.Tensor | None = None
        self._pid: int | None = None
        self._open: dict[int, Any] = {}

    @property
    def text_embedding(self) -> torch.Tensor:
        """The cached empty-prompt embedding (L, D) float32, read once per process."""
        if self._text is None:
            from safetensors.torch import load_file

            text = self.doc["text"]
            self._text = load_file(str(_file(self.build_dir, text["file"], "text embedding")))["text_embedding"]
        return self._text

    def _handle(self, shard: int) -> tuple[Any, list[str]]:
        from safetensors import safe_open

        if self._pid != os.getpid():  # a DataLoader worker: its own handles
            self._pid, self._open = os.getpid(), {}
        if shard not in self._open:
            path = self.shards[shard].path
            if not path.is_file():
                raise ParaDriveError(f"{path} is listed in {latents_index_path(self.build_dir)} but "
                                     f"missing; {_ENCODE_FIX} again")
            handle = safe_open(str(path), framework="pt", device="cpu")
            self._open[shard] = (handle, json.loads(handle.metadata()["pair_ids"]))
        return self._open[shard]

    def sample(self, i: int, row: dict) -> dict:
        """Pair ``i``'s latent sample; ``row`` is its manifest row (pair_id, offset_m, ...)."""
        shard = int(np.searchsorted(self._starts, i, side="right") - 1)
        handle, ids = self._handle(shard)
        local = i - self.shards[shard].start
        if ids[local] != row["pair_id"]:
            raise ParaDriveError(f"{self.shards[shard].path}: pair {local} is {ids[local]}, the build's "
                                 f"pair {i} is {row['pair_id']}; {_ENCODE_FIX} again")
        videos = handle.get_slice("pair_videos")[local:local + 1][0].tolist()
        stacked = handle.get_slice("latents")
        sample: dict[str, Any] = {f"{role}_latents": _widened(stacked[v:v + 1][0], self.dtype)
                                  for role, v in zip(LATENT_ROLES, videos) if v >= 0}
        rel = handle.get_slice("rel_pose")[local:local + 1][0]
        pose = torch.eye(4, dtype=torch.float32, device="cpu").repeat(rel.shape[0], 1, 1)
        pose[:, :3, :4] = rel.view(-1, 3, 4)
        sample.update(camera=handle.get_slice("camera")[local:local + 1][0], rel_pose=pose,
                      text_embedding=self.text_embedding, pair_id=row["pair_id"],
                      offset_m=float(row["offset_m"]), condition_iteration=int(row["condition_iteration"]),
                      prompt="")
        return sample


def collate_latents(samples: Sequence[dict]) -> dict:
    """A batch of latent samples: tensors stacked on a new first axis (latents (B, C, T', h, w),
    camera (B, T', 12), rel_pose (B, T', 4, 4), text_embedding (B, L, D)), numbers as tensors,
    strings as lists. Every sample must have the same keys (an inference build's rows without a
    target cannot share a batch with rows that have one)."""
    keys = list(samples[0])
    if any(list(s) != keys for s in samples):
        raise ValueError("samples of one batch must have the same keys (a row without a target "
                         "mixed with rows that have one)")
    batch: dict[str, Any] = {}
    for key in keys:
        values = [s[key] for s in samples]
        if isinstance(values[0], torch.Tensor):
            batch[key] = torch.stack(values)
        elif isinstance(values[0], (int, float)) and not isinstance(values[0], bool):
            batch[key] = torch.tensor(values, device="cpu")
        else:
            batch[key] = values
    return batch


# --------------------------------------------------------------------------- checking

def verify_latents(build_dir: str | Path) -> dict:
    """Re-hash every file the latent index names: {"present", "checked_files", "problems"}
    (a build without latents has nothing to check; a cache of other pairs is a problem)."""
    build_dir = Path(build_dir)
    if not has_latents(build_dir):
        return {"present": False, "checked_files": 0, "problems": []}
    try:
        doc = read_latents_index(build_dir)
    except ParaDriveError as exc:
        return {"present": True, "checked_files": 1, "problems": [f"stale: {exc}"]}
    entries = [(e["file"], e, f"latent shard {k}") for k, e in enumerate(doc["shards"])]
    entries.append((doc["text"]["file"], doc["text"], "text embedding"))
    problems = []
    for rel, entry, what in entries:
        try:
            path = _file(build_dir, rel, what)
        except ParaDriveError as exc:
            problems.append(f"unsafe: {exc}")
            continue
        problem = _file_problem(path, entry, what)
        if problem:
            problems.append(problem)
    return {"present": True, "checked_files": len(entries) + 1, "problems": problems}


def _file_problem(path: Path, entry: dict, what: str) -> str | None:
    fix = f"{_ENCODE_FIX} again: it re-encodes what is damaged"
    if not path.is_file():
        return f"missing: {path} ({what}); {fix}"
    size = path.stat().st_size
    if size != entry["bytes"]:
        return f"corrupt: {path} ({what}) has {size} bytes, the latent index says {entry['bytes']}; {fix}"
    actual = sha256_file(path)
    if actual != entry["sha256"]:
        return (f"corrupt: {path} ({what}) sha256 {actual[:12]}… differs from the latent index's "
                f"{entry['sha256'][:12]}…; {fix}")
    return None


def latents_summary(build_dir: str | Path) -> str:
    """One line for ``paradrive inspect``: what the latent cache holds, or why there is none."""
    build_dir = Path(build_dir)
    if not has_latents(build_dir):
        return "latents: none (paradrive encode BUILD --vae DIR writes them)"
    try:
        doc = read_latents_index(build_dir)
    except ParaDriveError as exc:
        return f"latents: unusable: {exc}"
    totals = doc["totals"]
    return (f"latents: {totals['pairs']} pairs, {totals['videos']} videos in {len(doc['shards'])} "
            f"shards ({totals['bytes'] / 1e6:.1f} MB, {doc['dtype']}, shape {doc['latent_shape']} "
            f"from {doc['num_frames']} frames of {doc['size'][0]}x{doc['size'][1]}), VAE sha256 "
            f"{doc['vae']['sha256'][:12]}…, text embedding {doc['text']['shape']}")
