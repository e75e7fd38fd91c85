"""Hand-offs of a build to the trainers users run: ReCamMaster's, DiffSynth-Studio's and diffusers'.

``paradrive convert recammaster BUILD OUT``
    ReCamMaster's training layout (its ``train_recammaster.py``): one folder per pair,
    ``OUT/train/<pair_id>/videos/cam01.mp4`` (the source, the video to re-render) and ``cam02.mp4``
    (the target), ``OUT/train/<pair_id>/cameras/camera_extrinsics.json`` (per frame, each camera's
    4x4 matrix as a string of four bracketed rows, in the axes and units ReCamMaster's loader
    undoes: its parse gives back our OpenCV camera-to-world in metres), ``OUT/metadata.csv``
    (``file_name,text``: the target videos, empty prompts) and, with a VAE, each video's cached
    ``<video>.tensors.pth`` (``latents`` (16, T', h, w) bf16 normalised as Wan trainers cache
    them, ``prompt_emb`` ``{"context": (1, L, D)}`` bf16, ``image_emb`` ``{}``). Those are written
    with ``torch.save``, the format ReCamMaster reads: a hand-off file in its format, holding
    tensors only (it loads them with ``weights_only=True``); the builder's own outputs stay
    pickle-free.
``paradrive convert diffsynth BUILD OUT``
    DiffSynth-Studio's dataset form (``--dataset_base_path OUT --dataset_metadata_path
    OUT/metadata.csv``): ``metadata.csv`` and ``metadata.json`` with one row per pair: ``video``
    (the target), ``prompt`` (empty), ``source_video``, ``condition_video`` (paths relative to OUT,
    the files under ``OUT/videos/``), ``offset_m`` and ``camera`` (the relative pose per latent
    frame, 12 numbers each, as JSON text in the CSV, a list in the JSON).
``paradrive convert pixels BUILD OUT``
    one safetensors file per pair, ``OUT/<pair_id>.safetensors``, holding ``source`` /
    ``condition`` / ``target`` uint8 (3, F, H, W) (diffusers' channels-first video layout),
    ``camera`` (T', 12) and ``rel_pose`` (F, 4, 4) float32, and ``OUT/index.json`` listing them;
    :func:`read_pixel_pair` reads one back and :func:`collate_pixels` batches samples as
    (B, 3, F, H, W) in [-1, 1] for a diffusers pipeline or a custom loop.

Every output lands atomically (written under a temporary name, then renamed).
"""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from paradrive.data import PairDataset
from paradrive.io import atomic_path, path_inside, write_json, write_text
from paradrive.pairs import build_file
from paradrive.train.trainer import collate, frames_on
from paradrive.train.wan import relative_camera, to_channels_first

FORMATS = ("recammaster", "diffsynth", "pixels")
SOURCE_CAMERA, TARGET_CAMERA = "cam01", "cam02"


# -- poses -----------------------------------------------------------------------------------------
def recammaster_matrix(c2w: np.ndarray) -> np.ndarray:
    """The 4x4 matrix ReCamMaster's loader turns back into ``c2w`` (OpenCV camera-to-world, metres).

    Its loader transposes the stored matrix, reorders the columns (x, y, z, t) <- (1, 2, 0, 3),
    negates the new y column and divides the translation by 100 (its dataset's centimetres);
    this is the inverse of those steps."""
    c2w = np.asarray(c2w, dtype=np.float64)
    p = np.zeros((4, 4))
    p[:, 1] = c2w[:, 0]
    p[:, 2] = c2w[:, 1]
    p[:3, 2] *= -1.0
    p[:, 0] = c2w[:, 2]
    p[:, 3] = c2w[:, 3]
    p[:3, 3] *= 100.0
    return p.T


def recammaster_text(matrix: np.ndarray) -> str:
    """A 4x4 matrix as ReCamMaster's ``camera_extrinsics.json`` writes one: bracketed rows,
    ``"[a b c d] [e f g h] [i j k l] [m n o p] "``; ``repr`` keeps every float exact."""
    return "".join("[" + " ".join(repr(float(v)) for v in row) + "] " for row in matrix)


def recammaster_extrinsics(target_c2w: np.ndarray, source_c2w: np.ndarray) -> dict[str, dict[str, str]]:
    """``{"frame<k>": {"cam01": source, "cam02": target}}`` for every frame of the clip."""
    return {f"frame{k}": {SOURCE_CAMERA: recammaster_text(recammaster_matrix(s)),
                          TARGET_CAMERA: recammaster_text(recammaster_matrix(t))}
            for k, (t, s) in enumerate(zip(target_c2w, source_c2w))}


def _pair_c2w(row: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(target, source) camera-to-world (F, 4, 4) of a manifest row (source = target @ ΔT)."""
    target = np.asarray(row["target_c2w"], dtype=np.float64)
    return target, target @ np.asarray(row["rel_pose"], dtype=np.float64)


# -- files ------------------------------------------------------------------------------------------
def _place(src: Path, dst: Path) -> None:
    """``dst`` becomes a copy of ``src`` (a hard link where the filesystem allows: same bytes, no
    second copy of a build's videos), atomically."""
    with atomic_path(dst) as tmp:
        try:
            os.link(src, tmp)
        except OSError:
            shutil.copyfile(src, tmp)


def _video(ds: PairDataset, row: Mapping[str, Any], role: str) -> Path:
    return build_file(ds.build, row[f"{role}_uri"], f"{ds.build}: row {row['pair_id']} column {role}_uri", ds.index)


def _pair_dir(out: Path, pair_id: str, where: str) -> Path:
    """``out/<pair_id>``: a pair id from a shared build names a folder, so it must stay inside."""
    return path_inside(out, pair_id, where)


# -- ReCamMaster ------------------------------------------------------------------------------------
def to_recammaster(build: str | Path, out: str | Path, vae: Any = None,
                   text_embedding: torch.Tensor | None = None, limit: int | None = None) -> int:
    """Write ReCamMaster's layout for every pair (the first ``limit``; see the module
    docstring); with ``vae`` (a Wan VAE) and ``text_embedding`` ((L, D), the empty prompt's) also
    the cached ``.tensors.pth``. Returns the number of pairs."""
    from paradrive.wan.vae import encode_video

    ds = PairDataset(build, dtype="uint8")
    out = Path(out)
    names = []
    for i, pair_id in enumerate(ds.pair_ids[:limit]):
        row = ds.row(i)
        folder = _pair_dir(out / "train", pair_id, f"{build}: pair {pair_id}")
        videos = {SOURCE_CAMERA: _video(ds, row, "source"), TARGET_CAMERA: _video(ds, row, "target")}
        for cam, src in videos.items():
            _place(src, folder / "videos" / f"{cam}.mp4")
        target_c2w, source_c2w = _pair_c2w(row)
        write_json(folder / "cameras" / "camera_extrinsics.json", recammaster_extrinsics(target_c2w, source_c2w))
        if vae is not None:
            if text_embedding is None:
                raise ValueError("the cached tensors need the empty prompt's embedding: pass text_embedding")
            sample = ds[i]
            for cam, role in ((SOURCE_CAMERA, "source"), (TARGET_CAMERA, "target")):
                video = to_channels_first(frames_on(sample[role][None], vae.device))
                cached = {"latents": encode_video(vae, video)[0].to(torch.bfloat16).cpu(),
                          "prompt_emb": {"context": text_embedding[None].to(torch.bfloat16).cpu()},
                          "image_emb": {}}
                with atomic_path(folder / "videos" / f"{cam}.mp4.tensors.pth") as tmp:
                    torch.save(cached, tmp)
        names.append(f"{pair_id}/videos/{TARGET_CAMERA}.mp4")
    _write_csv(out / "metadata.csv", ["file_name", "text"], [{"file_name": n, "text": ""} for n in names])
    return len(names)


# -- DiffSynth-Studio -------------------------------------------------------------------------------
def to_diffsynth(build: str | Path, out: str | Path, limit: int | None = None) -> int:
    """Write DiffSynth-Studio's ``metadata.csv`` / ``metadata.json`` and the videos they name
    for every pair (the first ``limit``; see the module docstring). Returns the number of pairs."""
    ds = PairDataset(build, dtype="uint8")
    out = Path(out)
    rows = []
    for i, pair_id in enumerate(ds.pair_ids[:limit]):
        row = ds.row(i)
        folder = _pair_dir(out / "videos", pair_id, f"{build}: pair {pair_id}")
        paths = {}
        for role in ("target", "source", "condition"):
            _place(_video(ds, row, role), folder / f"{role}.mp4")
            paths[role] = f"videos/{pair_id}/{role}.mp4"
        rel = torch.from_numpy(np.array(row["rel_pose"], dtype=np.float32))[None]
        camera = relative_camera(rel)[0].tolist()
        rows.append({"video": paths["target"], "prompt": "", "source_video": paths["source"],
                     "condition_video": paths["condition"], "offset_m": float(row["offset_m"]),
                     "camera": camera})
    write_json(out / "metadata.json", rows)
    _write_csv(out / "metadata.csv", list(rows[0]) if rows else ["video", "prompt"],
               [{**r, "camera": json.dumps(r["camera"])} for r in rows])
    return len(rows)


def _write_csv(path: Path, columns: Sequence[str], rows: Sequence[Mapping[str, Any]]) -> None:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(columns), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text(path, text.getvalue())


# -- diffusers' pixel layout ------------------------------------------------------------------------
def to_pixels(build: str | Path, out: str | Path, num_frames: int | None = None,
              output_size: tuple[int, int] | None = None, limit: int | None = None) -> int:
    """One safetensors file per pair (the first ``limit``) in diffusers' (3, F, H, W) layout
    (see the module docstring), at ``num_frames`` / ``output_size`` (default: as stored).
    Returns the count."""
    from safetensors.torch import save_file

    ds = PairDataset(build, dtype="uint8", num_frames=num_frames, output_size=output_size)
    out = Path(out)
    files = []
    for i, pair_id in enumerate(ds.pair_ids[:limit]):
        sample = ds[i]
        tensors = {role: sample[role].permute(1, 0, 2, 3).contiguous()
                   for role in ("source", "condition", "target") if role in sample}
        tensors["camera"] = relative_camera(sample["rel_pose"][None])[0].contiguous()
        tensors["rel_pose"] = sample["rel_pose"].contiguous()
        path = path_inside(out, f"{pair_id}.safetensors", f"{build}: pair {pair_id}")
        with atomic_path(path) as tmp:
            save_file(tensors, str(tmp), metadata={"pair_id": pair_id, "offset_m": repr(sample["offset_m"])})
        files.append({"pair_id": pair_id, "file": f"{pair_id}.safetensors", "offset_m": sample["offset_m"]})
    write_json(out / "index.json", {"layout": "(3, F, H, W) uint8 per video; camera (T', 12) float32",
                                   "pairs": files})
    return len(files)


def read_pixel_pair(path: str | Path) -> dict[str, Any]:
    """One file of :func:`to_pixels` as a sample: the tensors and its ``pair_id`` / ``offset_m``."""
    from safetensors import safe_open
    from safetensors.torch import load_file

    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
    sample: dict[str, Any] = dict(load_file(str(path)))
    sample["pair_id"] = meta.get("pair_id", Path(path).stem)
    sample["offset_m"] = float(meta.get("offset_m", "nan"))
    return sample


def collate_pixels(samples: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """A DataLoader ``collate_fn`` giving diffusers' video layout: ``source`` / ``condition`` /
    ``target`` as (B, 3, F, H, W) float32 in [-1, 1] (uint8 frames normalised), other tensors
    stacked, the rest listed. Takes the adapter's samples ((F, 3, H, W) frames) or
    :func:`read_pixel_pair`'s ((3, F, H, W))."""
    batch = collate([dict(s) for s in samples])
    for role in ("source", "condition", "target"):
        if role in batch:
            frames = batch[role]
            if frames.shape[1] != 3:   # the adapter's frames-first layout
                frames = to_channels_first(frames)
            batch[role] = frames_on(frames, frames.device)
    return batch


def convert_build(fmt: str, build: Path, out: Path, *, vae: Path | None = None,
                  text_encoder: Path | None = None, num_frames: int | None = None,
                  limit: int | None = None) -> int:
    """Write ``build`` into ``out`` in the layout ``fmt`` names (one of :data:`FORMATS`); the
    number of pairs written."""
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}: use one of {', '.join(FORMATS)}")
    if not build.is_dir():
        raise FileNotFoundError(f"{build}: no such build folder (run 'paradrive build' first)")
    if fmt == "diffsynth":
        return to_diffsynth(build, out, limit)
    if fmt == "pixels":
        return to_pixels(build, out, num_frames=num_frames, limit=limit)
    model, embedding = None, None
    if vae is not None:
        from paradrive.wan.text import empty_prompt_embedding
        from paradrive.wan.vae import load_vae

        if text_encoder is None:
            raise ValueError("--vae needs --text-encoder: the cached tensors hold the empty prompt's embedding")
        model, embedding = load_vae(vae), empty_prompt_embedding(text_encoder)
    return to_recammaster(build, out, model, embedding, limit)
