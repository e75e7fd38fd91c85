"""The trainer's adapter: pairs of a published build as torch datasets.

``PairDataset`` (map-style) and ``PairIterableDataset`` (sharded over ranks and DataLoader
workers, deterministic shuffle, exact mid-epoch resume) read a build folder written by the
manifest stage (``<manifests>/<build>/index.json`` and the version folder it names, holding
``pairs-*.parquet`` + ``media/``; :mod:`paradrive.pairs` resolves it once, at open).

One sample (docs/manifest.md, "The dataset adapter")::

    source, condition, target   float32 (F, 3, H, W) in [-1, 1] (no target in an inference row without one);
                                with dtype="uint8": uint8 (F, 3, H, W) as stored, for the trainer to
                                normalise on its device (``to_unit_range``)
    rel_pose                    float32 (F, 4, 4)  T_{target<-source} per frame
    identity_pose               float32 (F, 4, 4)  identity
    intrinsics                  float32 (4,)       fx, fy, cx, cy at the output resolution
    offset_m                    float              lateral offset of the source (+ = left)
    condition_iteration         int                checkpoint that rendered the condition
    pair_id, prompt             str                prompt is '' unless given
    camera                      float32 (ceil(F/4), 12)   only with pose_format="recammaster[_per_frame]"

Frames are decoded with PyAV: the decoder seeks to the keyframe at or before the first frame
asked for and decodes forward, stopping after the last one, so a short window or a stride never
decodes a whole video it does not need. swscale converts each frame to planar RGB (and resizes it),
through one conversion context per video and with the decoder's thread count, and each plane
goes straight into the channels-first output: copied for uint8, converted and normalised in place
for a float type while the plane is still in cache (no interleaved array, no second pass over the
sample). That per-frame work is numpy's, never a torch op: torch would split each plane over its
intra-op threads, and where other work takes every core each such call waits for threads that
get no core (37 times slower), so the adapter keeps its speed in any process, whatever
``torch.get_num_threads()`` its caller left, and never changes it.

Opening a build checks each shard's sha256 against the index (``verify_shards``; once per
process while a shard's stat is the same, see :func:`paradrive.pairs.check_shards`), then reads
only the pair ids and URIs of its shards (the ids are kept as Arrow, the URIs checked once
each); a row's other columns and its poses are read with its row group when a sample needs
them, so a 115K-row build opens in 0.9–1.3 s on a shared 2-core machine and costs a worker
megabytes.
"""

from __future__ import annotations

import functools
import math
import os
import weakref
from pathlib import Path
from typing import Any
from collections.abc import Callable, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from torch.utils.data import DataLoader, Dataset, IterableDataset, get_worker_info

from paradrive import geometry
from paradrive.errors import ParaDriveError
from paradrive.io import PathEscapeError, check_relative, sha256_file
from paradrive.pairs import (SCHEMA, URI_COLUMNS, build_file, check_row_uris, check_shard_again,
                             check_shards, current_version, iter_shard, read_index, shard_paths)
from paradrive.video import each_frame
from paradrive.latents import LatentReader

__all__ = ["FramePool", "PairDataset", "PairIterableDataset", "PairLoader", "epoch_order", "frame_array",
           "output_geometry", "per_rank", "plane_sink",
           "recammaster_camera", "to_unit_range"]

# Columns of a row; they and the per-frame poses are read one row group at a time, when a
# sample needs them. Opening a build reads only the ids and URIs, to check them.
_ROW_COLUMNS = ("pair_id", "dataset", "scene_id", "camera", "clip", "num_frames", "fps", "width",
          "height", "intrinsics", "offset_m", "condition_iteration", "source_iteration",
          "source_uri", "source_sha256", "condition_uri", "condition_sha256", "target_uri",
          "target_sha256")
_POSE_COLUMNS = ("rel_pose", "target_c2w")
_CHECKED_COLUMNS = ("pair_id", *URI_COLUMNS)


def _check_uris(table: pa.Table, where: str) -> None:
    """``check_row_uris`` over a shard's rows, each distinct URI checked once.

    A video is named by many rows (a target serves every offset and checkpoint), so a 115K-row
    build holds about half as many distinct URIs as rows. The rows are turned into Python
    values only when a URI fails, to name the first row holding it, as checking every row does.
    """
    try:
        for column in URI_COLUMNS:
            for uri in table.column(column).unique().to_pylist():
                if uri is not None:  # an inference row may have no target
                    check_relative(uri, column)
    except PathEscapeError:
        check_row_uris(table.to_pydict(), where)
        raise


_FRAME_DTYPES = {"uint8": torch.uint8, "float32": torch.float32, "float16": torch.float16,
                 "bfloat16": torch.bfloat16}


# --------------------------------------------------------------------------- frames

def _unit_range_into(out: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
    """uint8 ``frames`` written into float ``out`` as x / 127.5 - 1: the division converts, the
    subtraction is in place. Both steps are exact at 0 and 255 (a multiply by 1 / 127.5 with a
    fused add would give 255 -> 1.0000001)."""
    return torch.div(frames, 127.5, out=out).sub_(1.0)


@functools.cache
def _plane_writer(dtype: torch.dtype) -> Callable[[np.ndarray, np.ndarray], None]:
    """``write(channel, plane)``: a uint8 (H, W) colour plane into one channel of a frame buffer,
    given as a numpy view (16-bit floats as int16, see :func:`frame_array`).

    In numpy, which never splits one call over threads: a torch op on a frame this size spreads
    it over the intra-op threads, and on a machine whose cores are all busy every such call
    waits for threads that get no core (three 121-frame samples at 320x192: 21.6 s with torch's
    two threads, 0.58 s with one). Each float type gives exactly :func:`to_unit_range` of the
    uint8 plane: float32 by the same two correctly rounded steps (x / 127.5, then - 1), the
    16-bit types (which numpy computes slowly or lacks) by a table of those 256 values.
    """
    if dtype == torch.uint8:
        return np.copyto
    if dtype == torch.float32:
        def unit_range(channel: np.ndarray, plane: np.ndarray) -> None:
            np.divide(plane, np.float32(127.5), out=channel)
            np.subtract(channel, np.float32(1.0), out=channel)
        return unit_range
    table = frame_array(to_unit_range(torch.arange(256, dtype=torch.uint8, device="cpu"), dtype))

    def look_up(channel: np.ndarray, plane: np.ndarray) -> None:
        # a byte is always an index of the table: "wrap" never wraps, and unlike the default
        # ("raise") it writes straight into ``channel`` instead of through a buffer
        np.take(table, plane, out=channel, mode="wrap")
    return look_up


def frame_array(frames: torch.Tensor) -> np.ndarray:
    """A numpy view of CPU ``frames`` (float16 and bfloat16, which numpy lacks or computes
    slowly, as int16 bits) for :func:`plane_sink` to write into."""
    return (frames.view(torch.int16) if frames.element_size() == 2 else frames).numpy()


def plane_sink(channels: Callable[[int], np.ndarray], geo: dict,
               dtype: torch.dtype) -> Callable[[int, tuple[np.ndarray, ...]], None]:
    """A sink for ``each_frame(..., planar=True)``: frame ``idx``'s (R, G, B) planes, cut to
    ``geo``'s crop (:func:`output_geometry`), written as ``dtype`` into ``channels(idx)``, the
    frame's three (H, W) channels in a :func:`frame_array` view. No torch op runs per frame
    (see :func:`_plane_writer`)."""
    write = _plane_writer(dtype)
    oh, ow = geo["size"]
    y0, x0 = geo["crop"]

    def sink(idx: int, planes: tuple[np.ndarray, ...]) -> None:
        for channel, plane in zip(channels(idx), planes):
            write(channel, plane[y0:y0 + oh, x0:x0 + ow])
    return sink


class FramePool:
    """Frame buffers that the adapter fills again once nothing holds the sample they went out in.

    A 3 x 121 x 480 x 832 float32 sample is 1.7 GB; written into fresh memory, faulting those
    pages in costs more than decoding the videos. A buffer goes out as ``torch.from_numpy`` of a
    numpy view of it, and torch keeps that view alive for as long as any tensor shares its storage
    (the sample, a slice of it, a batch made of views), so the buffer is free again exactly when
    that view is gone, which a weak reference tells. At most ``keep`` buffers of a shape and dtype
    are kept (a sample takes three; a loop holding the previous sample while reading the next
    needs six); past that, or with ``keep=0``, buffers are plain allocations. Held memory goes
    with :meth:`clear` or the dataset. Per process: a pickled pool (a DataLoader worker) starts
    empty.
    """

    def __init__(self, keep: int = 6):
        self.keep = keep
        self._slots: dict[tuple, list[list]] = {}   # (shape, dtype) -> [[buffer, weakref | None]]

    def take(self, shape: tuple[int, ...], dtype: torch.dtype) -> torch.Tensor:
        """An uninitialised CPU tensor of ``shape`` and ``dtype``, reused when one is free."""
        slots = self._slots.setdefault((tuple(shape), dtype), [])
        free = next((s for s in slots if s[1] is None or s[1]() is None), None)
        if free is None and len(slots) >= self.keep:
            return torch.empty(shape, dtype=dtype, device="cpu")
        if free is None:
            # bfloat16, which numpy lacks, is kept as 16-bit integers and viewed
            held = torch.int16 if dtype == torch.bfloat16 else dtype
            free = [torch.empty(shape, dtype=held, device="cpu").numpy(), None]
            slots.append(free)
        view = free[0].view()
        free[1] = weakref.ref(view)
        tensor = torch.from_numpy(view)
        return tensor.view(dtype) if tensor.dtype != dtype else tensor

    def held_bytes(self) -> int:
        """Bytes of the buffers kept, in use or not."""
        return sum(s[0].nbytes for slots in self._slots.values() for s in slots)

    def clear(self) -> None:
        """Let go of every kept buffer (tensors still out keep theirs until they go)."""
        self._slots = {}

    def __getstate__(self) -> dict:
        return {"keep": self.keep, "_slots": {}}


def to_unit_range(frames: torch.Tensor, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """uint8 frames (any shape, any device) as ``dtype`` in [-1, 1], on the frames' device.

    What a trainer applies to ``dtype="uint8"`` samples after moving them to its device; the
    adapter's float output is exactly this of its uint8 output.
    """
    if frames.dtype != torch.uint8:
        raise TypeError(f"to_unit_range takes uint8 frames, got {frames.dtype}")
    return _unit_range_into(torch.empty(frames.shape, dtype=dtype, device=frames.device), frames)


def _is_integer(value: object, least: int) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool) and bool(value >= least)


def _is_size(value: object) -> bool:
    return (value is None or isinstance(value, (tuple, list)) and len(value) == 2
            and all(_is_integer(v, 1) for v in value))


# name -> (accepted(value), what is accepted): every argument of PairDataset
_PAIR_CHECKS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "num_frames": (lambda v: v is None or _is_integer(v, 1),
                   "an integer >= 1, or None (every frame of the clip from frame_offset)"),
    "frame_stride": (lambda v: _is_integer(v, 1), "an integer >= 1 (take every n-th frame)"),
    "frame_offset": (lambda v: _is_integer(v, 0), "an integer >= 0 (the window's first frame in the clip)"),
    "output_size": (_is_size, "(height, width), two integers >= 1, or None (as stored)"),
    "resize": (lambda v: v in ("crop", "stretch"), "'crop' or 'stretch'"),
    "pose_format": (lambda v: v in (None, "recammaster", "recammaster_per_frame"),
                    "None or 'recammaster' or 'recammaster_per_frame'"),
    "prompt": (lambda v: isinstance(v, str), "a string ('' as in the paper)"),
    "verify_checksums": (lambda v: isinstance(v, bool), "True or False"),
    "verify_shards": (lambda v: isinstance(v, bool), "True or False"),
    "decode_threads": (lambda v: _is_integer(v, 0), "an integer >= 0 (1: one decoder thread; 0: FFmpeg picks)"),
    "dtype": (lambda v: (_FRAME_DTYPES.get(v) if isinstance(v, str) else v) in _FRAME_DTYPES.values(),
              f"one of {', '.join(_FRAME_DTYPES)} (or the torch dtype)"),
    "reuse_buffers": (lambda v: isinstance(v, bool), "True or False"),
    "latents": (lambda v: isinstance(v, bool), "True or False"),
}

_FIXED_AT_ENCODE = ("the latent cache fixed the frames and their size when it was encoded "
                    "(paradrive encode --set encode.num_frames=N --set encode.size=[H,W])")
# with latents=True: name -> (accepted(value), why not otherwise)
_LATENT_CHECKS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "num_frames": (lambda v: v is None, _FIXED_AT_ENCODE),
    "frame_stride": (lambda v: v == 1, _FIXED_AT_ENCODE),
    "frame_offset": (lambda v: v == 0, _FIXED_AT_ENCODE),
    "output_size": (lambda v: v is None, _FIXED_AT_ENCODE),
    "prompt": (lambda v: v == "", "the latent cache holds the text embedding of the empty prompt "
                                  "alone (the paper trains with ''); read frames (latents=False), whose "
                                  "samples carry the prompt, to embed another one"),
    "dtype": (lambda v: v not in ("uint8", torch.uint8), "latents are floating point: use float32, "
                                                          "bfloat16 or float16"),
}


def _check_arguments(owner: str, checks: dict[str, tuple[Callable[[Any], bool], str]], given: dict) -> None:
    """Arguments checked before any file is read: a ValueError of one line naming the first wrong
    one, its value as given and what is accepted."""
    for name, (accepted, text) in checks.items():
        if not accepted(given[name]):
            raise ValueError(f"{owner}({name}={given[name]!r}): must be {text}")


def _check_pair_arguments(arguments: dict) -> None:
    """PairDataset's arguments (see :func:`_check_arguments`), and with ``latents=True`` none that
    a latent sample cannot honour."""
    _check_arguments("PairDataset", _PAIR_CHECKS, arguments)
    if arguments["latents"]:
        for name, (accepted, why) in _LATENT_CHECKS.items():
            if not accepted(arguments[name]):
                raise ValueError(f"PairDataset(latents=True, {name}={arguments[name]!r}): {why}; "
                                 f"leave {name} out")


# name -> (accepted(value), what is accepted): PairIterableDataset's own arguments
_ITERABLE_CHECKS: dict[str, tuple[Callable[[Any], bool], str]] = {
    "seed": (lambda v: _is_integer(v, 0), "an integer >= 0"),
    "shuffle": (lambda v: isinstance(v, bool), "True or False"),
    "world_size": (lambda v: v is None or _is_integer(v, 1), "an integer >= 1, or None (torch.distributed's, else 1)"),
    "rank": (lambda v: v is None or _is_integer(v, 0), "an integer >= 0, or None (torch.distributed's, else 0)"),
    "batch_size": (lambda v: _is_integer(v, 1), "an integer >= 1 (the DataLoader's batch_size)"),
    "partition": (lambda v: v in ("pad", "drop"), "'pad' or 'drop'"),
}


def _frame_dtype(dtype: torch.dtype | str) -> torch.dtype:
    resolved = _FRAME_DTYPES.get(dtype) if isinstance(dtype, str) else dtype
    if resolved is None or resolved not in _FRAME_DTYPES.values():
        raise ValueError(f"dtype must be one of {', '.join(_FRAME_DTYPES)} (or the torch dtype), "
                         f"got {dtype!r}")
    return resolved


# --------------------------------------------------------------------------- geometry

def output_geometry(width: int, height: int, output_size: tuple[int, int] | None,
                    resize: str = "crop") -> dict:
    """How a (height, width) frame becomes ``output_size`` = (H, W).

    ``crop``: scale uniformly so the frame covers (H, W), then cut the centre; ``stretch``: scale
    each axis to fit. Returns the intermediate size (rh, rw), the crop origin (y0, x0) and the
    per-axis scales (sx, sy); intrinsics follow docs/conventions.md: fx, cx scale by sx, fy, cy by sy, and
    the crop shifts cx, cy.
    """
    if output_size is None:
        return {"resize": None, "crop": (0, 0), "sx": 1.0, "sy": 1.0, "size": (height, width)}
    oh, ow = int(output_size[0]), int(output_size[1])
    if resize == "stretch":
        rh, rw = oh, ow
    elif resize == "crop":
        s = max(ow / width, oh / height)
        rh, rw = max(oh, round(height * s)), max(ow, round(width * s))
    else:
        raise ValueError(f"resize must be 'crop' or 'stretch', got {resize!r}")
    return {"resize": None if (rh, rw) == (height, width) else (rh, rw),
            "crop": ((rh - oh) // 2, (rw - ow) // 2), "sx": rw / width, "sy": rh / height,
            "size": (oh, ow)}


def adjust_intrinsics(intrinsics: Sequence[float], geo: dict) -> np.ndarray:
    f_x, f_y, c_x, c_y = (float(v) for v in intrinsics)
    fx, fy, cx, cy = geometry.scale_intrinsics(f_x, f_y, c_x, c_y, geo["sx"], geo["sy"])
    y0, x0 = geo["crop"]
    return np.array([fx, fy, cx - x0, cy - y0], dtype=np.float32)


def recammaster_camera(target_c2w: np.ndarray, source_c2w: np.ndarray, every: int = 4) -> np.ndarray:
    """ReCamMaster-style camera condition: (ceil(F / every), 12).

    Row k is ``(inv(source_c2w[0]) @ target_c2w[every * k])[:3, :4]`` flattened row-major: the
    pose of the target camera at frame ``every*k`` in the coordinates of the source camera at the
    sample's first frame (OpenCV axes, metres, no scale normalisation). ``every = 4`` gives one
    pose per Wan latent frame (31 for 121 frames).
    target_c2w, source_c2w: (F, 4, 4) camera-to-world of the sample's frames.
    """
    rel = geometry.invert(source_c2w[0]) @ geometry.as_pose(target_c2w[::every])
    return rel[:, :3, :4].reshape(-1, 12).astype(np.float32)


# --------------------------------------------------------------------------- map-style

class PairDataset(Dataset):
    """Map-style dataset over a build: ``ds[i]`` is the i-th pair in pair_id order.

    Args:
        build: the build folder (``<manifests>/<build>``, holding ``index.json``).
        num_frames: frames per sample (None = every frame of the clip from ``frame_offset``).
        frame_stride: take every n-th frame.
        frame_offset: first frame of the window within the clip.
        output_size: (height, width) of the output frames (None = as stored).
        resize: ``crop`` (uniform scale + centre crop, default) or ``stretch``.
        pose_format: None, or ``recammaster`` to add ``camera`` (see ``recammaster_camera``), or
            ``recammaster_per_frame`` (the target in the source's camera at the same frame,
            :func:`paradrive.geometry.recammaster_per_frame_camera`).
        prompt: the text every sample carries ('' as in the paper). With ``latents=True`` only
            '' is accepted: the cache holds the empty prompt's text embedding alone, so another
            prompt would be carried beside an embedding that is not its own.
        verify_checksums: check each video's sha256 against the manifest the first time this
            process reads it (a mismatch raises, naming the file).
        verify_shards: check each pair shard's sha256 against ``index.json`` when the build is
            opened (default True): a shard whose bytes changed since it was published raises
            :class:`paradrive.pairs.ShardChecksumError`, naming the shard, the build and the
            fix (a plain ``paradrive build``), before any of its rows is read. A shard is hashed
            once per process while its stat is the same; a DataLoader worker re-hashes only a
            shard whose stat changed since the dataset was opened. False reads the rows as they
            are (``paradrive inspect --verify`` still finds the damage).
        decode_threads: decoder threads per video (1 = one, suits DataLoader workers; n > 1 or
            0 = FFmpeg's frame and slice threads, 0 letting FFmpeg pick how many).
        dtype: type of the frame tensors: ``"uint8"`` (0..255 as stored, a quarter of float32's
            bytes; the trainer normalises on its device with ``to_unit_range``), or a float type
            in [-1, 1]: ``"float32"``, ``"bfloat16"``, ``"float16"`` (or the torch dtype). A
            3 x 121 x 480 x 832 sample is 0.43 GB in uint8, 1.7 GB in float32.
        reuse_buffers: fill the frame buffers of a sample nothing holds any more instead of fresh
            memory (:class:`FramePool`, ``buffers``; up to six videos' buffers stay allocated
            between samples: 3.5 GB in float32 at 480 x 832). False allocates every sample anew.
        latents: samples from the build's Wan2.1 latent cache (``paradrive encode``) instead of
            videos: ``target_latents``, ``source_latents``, ``condition_latents`` (C, T', h, w) in
            ``dtype``, ``camera``, ``rel_pose``, ``text_embedding`` (:class:`paradrive.latents.LatentReader`);
            the frame options (num_frames, frame_stride, frame_offset, output_size) are refused,
            since the cache fixed frames and size when it was encoded, and so is a prompt.
        version: the version folder to read (``v-<nnnnnn>``, while a publish keeps it); None
            reads the one ``index.json`` names at open. Either way the dataset reads that one
            version to the end, whatever is published meanwhile (:attr:`version` says which).

    Every argument is checked before the build is opened: a wrong one raises ValueError with one
    line naming it, its value and what it accepts.

    ``frames_decoded`` counts the frames the decoder produced in this process (those before a
    window included), so a caller can see what seeking saved.
    """

    def __init__(self, build: str | Path, *, num_frames: int | None = None, frame_stride: int = 1,
                 frame_offset: int = 0, output_size: tuple[int, int] | None = None,
                 resize: str = "crop", pose_format: str | None = None, prompt: str = "",
                 verify_checksums: bool = False, verify_shards: bool = True, decode_threads: int = 1,
                 dtype: torch.dtype | str = torch.float32, reuse_buffers: bool = True,
                 latents: bool = False, version: str | None = None):
        _check_pair_arguments({
            "num_frames": num_frames, "frame_stride": frame_stride, "frame_offset": frame_offset,
            "output_size": output_size, "resize": resize, "pose_format": pose_format, "prompt": prompt,
            "verify_checksums": verify_checksums, "verify_shards": verify_shards,
            "decode_threads": decode_threads, "dtype": dtype, "reuse_buffers": reuse_buffers,
            "latents": latents})
        self.build = Path(build)
        self.index = read_index(self.build, version)   # resolved once: every read stays in it
        self.num_frames, self.frame_stride, self.frame_offset = num_frames, frame_stride, frame_offset
        self.output_size = None if output_size is None else (int(output_size[0]), int(output_size[1]))
        self.resize = resize
        self.pose_format, self.prompt, self.verify_checksums = pose_format, prompt, verify_checksums
        self.decode_threads = decode_threads
        self.dtype = _frame_dtype(dtype)
        self.frames_decoded = 0
        self.buffers = FramePool() if reuse_buffers else FramePool(keep=0)
        self._shards = shard_paths(self.build, self.index)
        # the stat of each shard whose sha256 matched the index: a worker's copy re-hashes a
        # shard only when its stat differs (None: verify_shards=False)
        self._stamps = check_shards(self.build, self.index, self._shards) if verify_shards else None
        # one Arrow string array a shard: pa.chunked_array would import pandas into every worker
        self._pair_ids = [self._checked_pair_ids(path, entry.rows)
                          for path, entry in zip(self._shards, self.index.shards)]
        self._starts = np.cumsum([0] + [len(ids) for ids in self._pair_ids])
        self._pid: int | None = None
        self._files: dict[int, Any] = {}
        self._group_cache: dict[tuple[int, int], dict] = {}
        self._verified: set[str] = set()
        # latents=True: samples from the build's latent cache (paradrive.latents), no video
        self.latents = LatentReader(self.build, self.index, self.pair_ids, self.dtype) if latents else None

    def _checked_pair_ids(self, path: Path, rows: int) -> pa.Array:
        """The pair ids of one shard, after its row count and URIs are checked.

        Only ``pair_id`` and the URIs are read here, and only the ids are kept (one Arrow
        string array): a row's other columns come with its row group when a sample is read
        (:meth:`row`), so a 115K-row build costs its workers megabytes, not a Python object
        per value.
        """
        if not path.is_file():
            raise ParaDriveError(f"{path} is listed in {self.build / 'index.json'} but missing;"
                                 f" re-run the manifest stage or re-publish the build")
        batches = list(iter_shard(path, _CHECKED_COLUMNS, batch_rows=max(1, rows)))
        schema = pa.schema([SCHEMA.field(name) for name in _CHECKED_COLUMNS])
        table = pa.Table.from_batches(batches, schema=schema)
        if table.num_rows != rows:
            raise ParaDriveError(f"{path} has {table.num_rows} rows, index.json says "
                                 f"{rows}; the build is inconsistent, re-run the "
                                 f"manifest stage")
        _check_uris(table, str(path))
        return table.column("pair_id").combine_chunks()

    def __getstate__(self) -> dict:
        """What a DataLoader worker receives: open files and cached row groups stay behind."""
        return {**self.__dict__, "_pid": None, "_files": {}, "_group_cache": {}}

    # ------------------------------------------------------------ rows
    def __len__(self) -> int:
        return int(self._starts[-1])

    @property
    def version(self) -> str | None:
        """The version folder this dataset reads (None: a build published before versions)."""
        return self.index.version

    @property
    def pair_ids(self) -> list[str]:
        """Every pair id in order (a new list per call: the dataset keeps them as Arrow)."""
        return [pair_id for ids in self._pair_ids for pair_id in ids.to_pylist()]

    def row(self, i: int) -> dict:
        """The manifest row of pair i (light columns plus ``rel_pose`` and ``target_c2w`` (N, 4, 4))."""
        if not 0 <= i < len(self):
            raise IndexError(f"pair index {i} out of range for {len(self)} pairs")
        cols, offset = self._row_group(i)
        row = {name: cols[name][offset].as_py() for name in _ROW_COLUMNS}
        for name in _POSE_COLUMNS:
            values = cols[name][offset].values.flatten().to_numpy(zero_copy_only=False)
            row[name] = values.reshape(-1, 4, 4)
        return row

    def _row_group(self, i: int) -> tuple[dict, int]:
        """The columns of the row group holding pair i (a few kept per process) and i's place in it."""
        if self._pid != os.getpid():  # after a fork (DataLoader workers) reopen the files
            self._pid, self._files, self._group_cache = os.getpid(), {}, {}
        shard = int(np.searchsorted(self._starts, i, side="right") - 1)
        local = i - int(self._starts[shard])
        f = self._files.get(shard)
        if f is None:
            if self._stamps is not None:
                check_shard_again(self.build, self.index, shard, self._shards[shard], self._stamps[shard])
            f = self._files[shard] = pq.ParquetFile(self._shards[shard])
        meta = f.metadata
        group, offset = 0, local
        while offset >= meta.row_group(group).num_rows:
            offset -= meta.row_group(group).num_rows
            group += 1
        key = (shard, group)
        cols = self._group_cache.get(key)
        if cols is None:
            table = f.read_row_group(group, columns=[*_ROW_COLUMNS, *_POSE_COLUMNS])
            cols = {name: table.column(name) for name in table.column_names}
            if len(self._group_cache) >= 4:
                self._group_cache.pop(next(iter(self._group_cache)))
            self._group_cache[key] = cols
        return cols, offset

    def frame_indices(self, clip_frames: int) -> list[int]:
        """Frames of the clip a sample uses (0-based within the clip)."""
        n = self.num_frames
        if n is None:
            n = (clip_frames - 1 - self.frame_offset) // self.frame_stride + 1
        frames = [self.frame_offset + k * self.frame_stride for k in range(n)]
        if n < 1 or frames[-1] >= clip_frames:
            raise ValueError(f"window of {n} frames from {self.frame_offset} every "
                             f"{self.frame_stride} needs {frames[-1] + 1 if n > 0 else '?'} frames; "
                             f"the clip has {clip_frames}: lower num_frames/frame_stride/frame_offset")
        return frames

    # ------------------------------------------------------------ samples
    def _video(self, uri: str, sha: str, frames: list[int], geo: dict, what: str) -> torch.Tensor:
        path = build_file(self.build, uri, what, self.index)
        if self.verify_checksums and uri not in self._verified:
            if not path.is_file():
                raise ParaDriveError(f"{path} is missing; restore it or re-run the manifest stage")
            actual = sha256_file(path)
            if actual != sha:
                raise ParaDriveError(f"{path}: sha256 {actual[:12]}… does not match the "
                                     f"manifest ({sha[:12]}…); the file is corrupt, re-run the "
                                     f"manifest stage or restore it")
            self._verified.add(uri)
        out = self.buffers.take((len(frames), 3, *geo["size"]), self.dtype)
        array = frame_array(out)
        position = {f: k for k, f in enumerate(frames)}
        stats: dict = {}
        each_frame(path, frames, plane_sink(lambda idx: array[position[idx]], geo, self.dtype),
                   size=geo["resize"], threads=self.decode_threads, stats=stats, planar=True)
        self.frames_decoded += stats.get("decoded", 0)
        return out

    def __getitem__(self, i: int) -> dict:
        row = self.row(int(i))
        if self.latents is not None:
            return self.latents.sample(int(i), row)
        frames = self.frame_indices(int(row["num_frames"]))
        geo = output_geometry(int(row["width"]), int(row["height"]), self.output_size, self.resize)
        # an inference row of a real log has no target: the novel view is unknown
        sample = {role: self._video(row[f"{role}_uri"], row[f"{role}_sha256"], frames, geo,
                                    f"{self.build}: row {row['pair_id']} column {role}_uri")
                  for role in ("source", "condition", "target") if row[f"{role}_uri"] is not None}
        rel = row["rel_pose"][frames]
        f = len(frames)
        sample.update(**{
            "rel_pose": torch.from_numpy(np.ascontiguousarray(rel, dtype=np.float32)),
            "identity_pose": torch.eye(4, device="cpu").expand(f, 4, 4).clone(),
            "intrinsics": torch.from_numpy(adjust_intrinsics(row["intrinsics"], geo)),
            "offset_m": float(row["offset_m"]),
            "condition_iteration": int(row["condition_iteration"]),
            "pair_id": row["pair_id"],
            "prompt": self.prompt,
        })
        if self.pose_format == "recammaster":
            target_c2w = row["target_c2w"][frames]
            source_c2w = target_c2w @ rel.astype(np.float64)
            sample["camera"] = torch.from_numpy(recammaster_camera(target_c2w, source_c2w))
        if self.pose_format == "recammaster_per_frame":   # inv(rel_pose) per latent frame (paradrive.geometry)
            sample["camera"] = torch.from_numpy(geometry.recammaster_per_frame_camera(rel, every=4))
        return sample


# --------------------------------------------------------------------------- iterable

def epoch_order(num_pairs: int, seed: int, epoch: int, world_size: int = 1, shuffle: bool = True,
                partition: str = "pad") -> np.ndarray:
    """The pair indices of one epoch over every rank, (``per_rank(...) * world_size``,): a
    permutation drawn from ``(seed, epoch)`` (pair_id order with ``shuffle=False``) padded by its
    first elements or cut to a multiple of ``world_size``; rank r reads elements r, r + world_size, ...
    (``[r::world_size]``). The one order of :class:`PairIterableDataset` and the trainers."""
    order = (np.random.default_rng([int(seed), int(epoch)]).permutation(num_pairs) if shuffle
             else np.arange(num_pairs))
    return np.resize(order, per_rank(num_pairs, world_size, partition) * world_size)


def per_rank(num_pairs: int, world_size: int, partition: str = "pad") -> int:
    """Samples each rank reads per epoch: ``ceil(n / w)`` (``pad``) or ``n // w`` (``drop``)."""
    return math.ceil(num_pairs / world_size) if partition == "pad" else num_pairs // world_size


def _dist_rank_world() -> tuple[int, int]:
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        return torch.distributed.get_rank(), torch.distributed.get_world_size()
    return 0, 1


class PairIterableDataset(IterableDataset):
    """Pairs of a build split over distributed ranks and DataLoader workers.

    Order. Epoch e visits a permutation of all pairs drawn from ``(seed, e)`` (or pair_id order
    with ``shuffle=False``). The epoch sequence is made a multiple of ``world_size`` —
    ``partition="pad"`` repeats its first samples, ``"drop"`` leaves out its last ones — and rank
    r takes elements r, r + world_size, ... so every rank yields ``len(self)`` samples (DDP never
    waits on a rank that ran out).

    Workers. A rank's sequence is cut into batches of ``batch_size`` (pass the DataLoader's) and
    worker w takes batches w, w + num_workers, ...: a DataLoader collecting from its workers in
    turn then delivers the rank's sequence in order, so "samples consumed" is an exact position.

    Resume. ``state_dict(samples_consumed)`` records the epoch, the samples of this rank's
    epoch sequence already used and the build version read; after ``load_state_dict`` (which
    opens that version again, while a publish keeps it) the next iterator of that epoch starts
    right after them. Read it through :class:`PairLoader`, whose ``state_dict()`` counts the
    samples the loop received, with or without workers. Under a plain DataLoader the dataset
    counts by itself only with ``num_workers=0``: with workers the samples are drawn by the
    workers' copies, which the main process cannot see, so its own count stays 0 and the
    caller must pass the number its loader delivered since the iterator started.
    ``set_epoch(e)`` before each epoch (as with DistributedSampler).

    A republished build. The dataset reads the version it opened to the end, however often the
    build is published meanwhile (a publish keeps it for ``manifest.keep_versions_for``). To
    pick up a new version, call ``set_epoch(e, refresh=True)``: at that epoch boundary, and only
    there, it opens the version ``index.json`` names now (every rank must then see the same
    one: refresh on all ranks at the same boundary). DataLoader workers get the new version
    with their next iterator, unless ``persistent_workers=True`` keeps their old copy.

    Args (beyond PairDataset's, which pass through): seed, shuffle, rank, world_size (default
    from torch.distributed when initialised, else 0 and 1), batch_size, partition.
    """

    def __init__(self, build: str | Path, *, seed: int = 0, shuffle: bool = True,
                 rank: int | None = None, world_size: int | None = None, batch_size: int = 1,
                 partition: str = "pad", **pair_options):
        super().__init__()
        _check_arguments("PairIterableDataset", _ITERABLE_CHECKS, {
            "seed": seed, "shuffle": shuffle, "rank": rank, "world_size": world_size,
            "batch_size": batch_size, "partition": partition})
        self._options = {k: v for k, v in pair_options.items() if k != "version"}
        drank, dworld = _dist_rank_world()
        self.rank = drank if rank is None else int(rank)
        self.world_size = dworld if world_size is None else int(world_size)
        if not 0 <= self.rank < self.world_size:
            raise ValueError(f"PairIterableDataset(rank={self.rank}): must be below world_size "
                             f"({self.world_size}): ranks are 0 .. world_size - 1")
        self.dataset = PairDataset(build, **pair_options)
        if partition == "drop" and len(self.dataset) < self.world_size:
            raise ValueError(f"partition='drop' with {len(self.dataset)} pairs and "
                             f"{self.world_size} ranks leaves nothing; use partition='pad'")
        self.seed, self.shuffle, self.batch_size, self.partition = seed, shuffle, batch_size, partition
        self.epoch = 0
        self._resume: tuple[int, int] | None = None   # (epoch, samples already consumed)
        self._yielded = 0                              # counted here when iterated in-process

    # ------------------------------------------------------------ order
    def set_epoch(self, epoch: int, *, refresh: bool = False) -> bool:
        """Start epoch ``epoch``; with ``refresh``, first open the build's current version if a
        publish replaced the one read so far. Returns whether the version changed."""
        self.epoch = int(epoch)
        self._yielded = 0
        return self.refresh() if refresh else False

    @property
    def version(self) -> str | None:
        """The build version being read."""
        return self.dataset.version

    def refresh(self) -> bool:
        """Open the version ``index.json`` names now, if it is another; only between epochs (a
        resume point pending for this epoch keeps the version it was saved with)."""
        if self._resume is not None and self._resume[0] == self.epoch:
            return False
        now = current_version(self.dataset.build)
        if now is None or now == self.dataset.version:
            return False
        self._open(now)
        return True

    def _open(self, version: str) -> None:
        dataset = PairDataset(self.dataset.build, version=version, **self._options)
        if self.partition == "drop" and len(dataset) < self.world_size:
            raise ValueError(f"version {version} of {dataset.build} has {len(dataset)} pairs for "
                             f"{self.world_size} ranks: partition='drop' leaves nothing; use "
                             f"partition='pad'")
        self.dataset = dataset

    def __len__(self) -> int:
        """Samples each rank yields per epoch."""
        return per_rank(len(self.dataset), self.world_size, self.partition)

    def epoch_order(self, epoch: int | None = None) -> np.ndarray:
        """The whole epoch's sequence of pair indices (after padding or dropping)."""
        epoch = self.epoch if epoch is None else int(epoch)
        return epoch_order(len(self.dataset), self.seed, epoch, self.world_size, self.shuffle, self.partition)

    def rank_order(self, epoch: int | None = None) -> np.ndarray:
        """This rank's sequence of pair indices for the epoch."""
        return self.epoch_order(epoch)[self.rank::self.world_size]

    def _start(self) -> int:
        if self._resume is not None and self._resume[0] == self.epoch:
            return self._resume[1]
        return 0

    def worker_order(self, worker_id: int = 0, num_workers: int = 1,
                     epoch: int | None = None) -> np.ndarray:
        """Pair indices worker ``worker_id`` of ``num_workers`` yields (after any resume point)."""
        seq = self.rank_order(epoch)[self._start():]
        b = self.batch_size
        batches = np.arange(len(seq)) // b
        return seq[batches % num_workers == worker_id]

    def __iter__(self):
        info = get_worker_info()
        wid, nw = (info.id, info.num_workers) if info is not None else (0, 1)
        for i in self.worker_order(wid, nw):
            sample = self.dataset[int(i)]
            if info is None:
                self._yielded += 1
            yield sample

    # ------------------------------------------------------------ resume
    def state_dict(self, samples_consumed: int | None = None) -> dict:
        """Where this rank stands: the epoch and the samples of its epoch sequence used so far.

        samples_consumed: samples the loader delivered since the current iterator started
        (needed with DataLoader workers; :meth:`PairLoader.state_dict` passes it); None = the
        dataset's own count, right only with ``num_workers=0``.
        """
        used = self._yielded if samples_consumed is None else int(samples_consumed)
        return {"epoch": self.epoch, "samples_consumed": self._start() + used,
                "seed": self.seed, "shuffle": self.shuffle, "num_pairs": len(self.dataset),
                "rank": self.rank, "world_size": self.world_size, "partition": self.partition,
                "version": self.dataset.version}

    def load_state_dict(self, state: dict) -> None:
        """Resume from ``state_dict()`` of this rank: the same rank of the same world size (a
        state is one rank's position in its own sequence; the DataLoader's worker count is not
        part of it), the same seed, shuffle, partition and build; anything else is refused in
        one line before any version is opened."""
        self._check_rank(state)
        saved = state.get("version")
        if saved is not None and saved != self.dataset.version:
            try:   # the epoch goes on where it stopped: in the version it was reading
                self._open(saved)
            except ParaDriveError as exc:
                raise ValueError(f"cannot resume epoch {state.get('epoch')} mid-way: {exc}; or "
                                 f"start epoch {int(state.get('epoch', 0)) + 1} without the "
                                 f"saved state") from exc
        for key in ("seed", "shuffle", "num_pairs", "world_size", "partition"):
            mine = len(self.dataset) if key == "num_pairs" else getattr(self, key)
            if key in state and state[key] != mine:
                raise ValueError(f"cannot resume: the state was saved with {key}={state[key]!r}, "
                                 f"this dataset has {mine!r}; resume with the same build and "
                                 f"settings, or start a new epoch")
        consumed = int(state["samples_consumed"])
        if not 0 <= consumed <= len(self):
            raise ValueError(f"cannot resume: samples_consumed={consumed} outside 0..{len(self)}")
        self.epoch = int(state["epoch"])
        self._resume = (self.epoch, consumed)
        self._yielded = 0

    def _check_rank(self, state: dict) -> None:
        """A state saved by another rank, or under another world size, would resume this rank
        at another rank's position (or in a sequence cut for another number of ranks)."""
        rank, world = state.get("rank", self.rank), state.get("world_size", self.world_size)
        if (rank, world) != (self.rank, self.world_size):
            raise ValueError(f"cannot resume: the state was saved by rank {rank} of world_size "
                             f"{world}, and rank {self.rank} of world_size {self.world_size} is "
                             f"loading it; load each rank's own state_dict() with the same "
                             f"world_size, or start a new epoch")


def _batch_samples(batch: Any, default: int) -> int:
    """Samples in a collated batch: the length of its ``pair_id`` list (the last batch of an
    epoch may be short), else ``default``."""
    if isinstance(batch, dict) and isinstance(batch.get("pair_id"), (list, tuple)):
        return len(batch["pair_id"])
    if isinstance(batch, (list, tuple)) and batch and isinstance(batch[0], dict):
        return len(batch)
    return default


class PairLoader:
    """A ``DataLoader`` over a :class:`PairIterableDataset` whose ``state_dict()`` knows how many
    samples the loop has received, with any number of workers.

    ``for batch in loader`` iterates a DataLoader built with the dataset's ``batch_size`` and
    ``options`` (``num_workers``, ``collate_fn``, ``pin_memory``, ...); each batch is counted when
    it is handed to the loop, in the main process, so a state saved after a batch was used resumes
    right after it, however far the workers have read ahead. ``state_dict()`` /
    ``load_state_dict()`` are the dataset's, with that count passed in; a new iterator (a new
    epoch after ``set_epoch``, or the one after ``load_state_dict``) starts counting at 0.
    ``persistent_workers=True`` is refused: persistent workers keep the dataset copy of their
    first iterator, so they would not see a new epoch or a loaded state.
    """

    def __init__(self, dataset: PairIterableDataset, **options: Any):
        if not isinstance(dataset, PairIterableDataset):
            raise TypeError(f"PairLoader reads a PairIterableDataset, got {type(dataset).__name__}")
        size = options.pop("batch_size", dataset.batch_size)
        if size != dataset.batch_size:
            raise ValueError(f"PairLoader(batch_size={size}): the dataset cuts its workers' shares in "
                             f"batches of {dataset.batch_size}; give both the same batch_size")
        if options.get("persistent_workers"):
            raise ValueError("PairLoader(persistent_workers=True): persistent workers keep their first "
                             "copy of the dataset and would miss set_epoch and load_state_dict; leave it off")
        self.dataset = dataset
        self.loader = DataLoader(dataset, batch_size=dataset.batch_size, **options)
        self._received = 0
        self._epoch: int | None = None   # the epoch the current iterator reads

    def __iter__(self):
        self._epoch, self._received = self.dataset.epoch, 0
        for batch in self.loader:
            self._received += _batch_samples(batch, self.dataset.batch_size)
            yield batch

    def __len__(self) -> int:
        """Batches of a whole epoch (fewer after a resume point)."""
        return math.ceil(len(self.dataset) / self.dataset.batch_size)

    def state_dict(self) -> dict:
        """The dataset's state with the samples received since the current iterator began."""
        received = self._received if self._epoch == self.dataset.epoch else 0
        return self.dataset.state_dict(samples_consumed=received)

    def load_state_dict(self, state: dict) -> None:
        """Resume from ``state_dict()``: the next iterator starts right after the samples it counted."""
        self.dataset.load_state_dict(state)
        self._received, self._epoch = 0, None
