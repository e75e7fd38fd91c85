"""Hand-offs of a build to the trainers users run: ReCamMaster's, DiffSynth-Studio's and diffusers'.

``paradrive convert recammaster BUILD OUT``
    ReCamMaster's training layout (its ``train_recammaster.py``): one folder per pair,
    ``OUT/train/<pair_id>/videos/cam01.mp4`` (the source, the video to re-render) and ``cam02.mp4``
    (the target), ``OUT/train/<pair_id>/cameras/camera_extrinsics.json`` (per frame, each camera's
    4x4 matrix as a string of four bracketed rows, in the axes and units ReCamMaster's loader
    undoes: its parse gives back our OpenCV camera-to-world in metres), ``OUT/metadata.csv``
    (``file_name,text``: the target videos, the empty prompt written as one space, see
    :data:`EMPTY_PROMPT`) and each video's cached ``<video>.tensors.pth`` (``latents``
    (16, T', h, w) bf16 normalised as Wan trainers cache them, ``prompt_emb`` ``{"context":
    (1, L, D)}`` bf16, ``image_emb`` ``{}``), so a VAE is required: ReCamMaster's ``data_process``
    caches only the videos ``metadata.csv`` lists (the targets) and its loader needs the source's
    cache too. Those are written with ``torch.save``, the format ReCamMaster reads: a hand-off
    file in its format, holding tensors only (it loads them with ``weights_only=True``); the
    builder's own outputs stay pickle-free.
``paradrive convert diffsynth BUILD OUT``
    DiffSynth-Studio's dataset form (``--dataset_base_path OUT --dataset_metadata_path
    OUT/metadata.csv``): ``metadata.csv`` and ``metadata.json`` with one row per pair: ``video``
    (the target), ``prompt`` (:data:`EMPTY_PROMPT`), ``source_video``, ``condition_video`` (paths relative to OUT,
    the files under ``OUT/videos/``), ``offset_m`` and ``camera`` (the relative pose per latent
    frame, 12 numbers each, as JSON text in the CSV, a list in the JSON).
``paradrive convert pixels BUILD OUT``
    one safetensors file per pair, ``OUT/<pair_id>.safetensors``, holding ``source`` /
    ``condition`` / ``target`` uint8 (3, F, H, W) (diffusers' channels-first video layout),
    ``camera`` (T', 12) and ``rel_pose`` (F, 4, 4) float32, and ``OUT/index.json`` listing them;
    :func:`read_pixel_pair` reads one back and :func:`collate_pixels` batches samples as
    (B, 3, F, H, W) in [-1, 1] for a diffusers pipeline or a custom loop.

The export lands whole: it is written into a temporary folder beside OUT and renamed into place
when complete (an earlier export in OUT is replaced; a folder holding anything else is refused),
so a failed conversion (a full disk, a file-size limit) leaves nothing behind.
"""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from paradrive.data import PairDataset
from paradrive.latents import has_latents
from paradrive.io import atomic_path, path_inside, write_json, write_text
from paradrive.pairs import build_file, read_pairs
from paradrive.train.trainer import collate, frames_on
from paradrive.train.wan import relative_camera, to_channels_first

FORMATS = ("recammaster", "diffsynth", "pixels")
SOURCE_CAMERA, TARGET_CAMERA = "cam01", "cam02"
# the other cameras ReCamMaster's loader may draw as the condition: the source again
_CONDITION_CAMERAS = tuple(f"cam{k:02d}" for k in range(3, 11))
# The empty prompt as a metadata cell: pandas (how DiffSynth-Studio's and ReCamMaster's loaders
# read metadata.csv) reads an empty cell as NaN, which their tokenizer refuses; their Wan prompter
# strips whitespace first (clean='whitespace'), so one space encodes exactly as the empty prompt.
EMPTY_PROMPT = " "
# written last into every export: marks a folder convert may replace
MARKER = ".paradrive-convert.json"


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
    """``{"frame<k>": {"cam01": source, "cam02": target, "cam03" … "cam10": source}}`` for every
    frame of the clip (the condition cameras ReCamMaster's loader may draw are all the source)."""
    frames = {}
    for k, (t, s) in enumerate(zip(target_c2w, source_c2w)):
        source = recammaster_text(recammaster_matrix(s))
        frames[f"frame{k}"] = {SOURCE_CAMERA: source, TARGET_CAMERA: recammaster_text(recammaster_matrix(t)),
                               **{cam: source for cam in _CONDITION_CAMERAS}}
    return frames


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


def _pair_folders(ds: PairDataset, root: Path, build: str | Path,
                  limit: int | None) -> Iterator[tuple[int, str, Mapping[str, Any], Path]]:
    """The first ``limit`` pairs of ``ds``: index, pair id, row and folder ``root/<pair_id>`` (a
    pair id from a shared build names a folder, so it must stay inside; ``build`` as given names
    the pair in the refusal)."""
    for i, pair_id in enumerate(ds.pair_ids[:limit]):
        yield i, pair_id, ds.row(i), path_inside(root, pair_id, f"{build}: pair {pair_id}")


# -- ReCamMaster ------------------------------------------------------------------------------------
# What ReCamMaster's unmodified TensorDataset and DiT read: latents of 480x832 frames (its DiT's 30x52
# token grid), the cameras of frames range(81)[::4] (21 latent frames), and a condition camera drawn
# among cam01..cam10 (found by substituting the number in the target's path)
RECAMMASTER_SIZE = (480, 832)
RECAMMASTER_FRAMES = 81
RECAMMASTER_CAMERAS = 10
LATENTS_FOLDER = "latents"   # OUT/latents/<video sha256>.tensors.pth: each distinct video once


def check_recammaster_size(size: tuple[int, int] | None) -> None:
    """ValueError for a size ReCamMaster cannot read, before any work."""
    if size is not None and tuple(size) != RECAMMASTER_SIZE:
        raise ValueError(f"--size {size[0]}x{size[1]}: ReCamMaster's DiT reads a 30x52 token grid, the latents "
                         f"of 480x832 frames, and nothing else; leave --size out (480x832), or use convert "
                         f"pixels / diffsynth for another size")


def recammaster_frames(build: str | Path, num_frames: int | None) -> int:
    """Frames each video is encoded at: ``num_frames`` (4k + 1, at most every clip's), by default
    the 81 ReCamMaster's loader reads cameras for; ValueError before any work otherwise."""
    from paradrive.wan.vae import TEMPORAL_FACTOR

    shortest = min(read_pairs(build, ("num_frames",), verify=True).column("num_frames").to_pylist())
    frames = RECAMMASTER_FRAMES if num_frames is None else int(num_frames)
    if (frames - 1) % TEMPORAL_FACTOR:
        raise ValueError(f"--num-frames {frames} is not 4k + 1 (Wan's VAE encodes the first frame alone, then "
                         f"groups of 4): use 81, ReCamMaster's, or e.g. {1 + (shortest - 1) // 4 * 4}")
    if frames > shortest:
        raise ValueError(f"the build {build} has clips of {shortest} frames, and ReCamMaster reads {frames} "
                         f"(its loader takes the cameras of frames range({frames})[::4]): pass --num-frames "
                         f"{1 + (shortest - 1) // 4 * 4} and make that range({1 + (shortest - 1) // 4 * 4}) "
                         f"in its train_recammaster.py")
    return frames


class RecamLatents:
    """Each distinct video's ReCamMaster latents, once: from the build's encode cache when it
    fits (480x832, cropped, at least ``frames`` frames, by the same VAE), else by the VAE.

    ``vae`` / ``text_embedding``: the loaded VAE and the empty prompt's (L, D) embedding (None
    when the cache serves every video). ``encoded`` / ``from_cache`` count the videos each way."""

    def __init__(self, build: str | Path, frames: int, vae: Any = None, text_embedding: torch.Tensor | None = None,
                 cache: PairDataset | None = None):
        from paradrive.wan.vae import latent_frames

        self.build, self.frames, self.vae = build, frames, vae
        self.latent_frames = latent_frames(frames)
        self.cache = cache
        self.text = text_embedding if cache is None or cache.latents is None else cache.latents.text_embedding
        self.pixels: PairDataset | None = None   # the frames the VAE encodes, opened when first needed
        self.encoded = self.from_cache = 0

    def tensors(self, i: int, role: str) -> dict[str, Any]:
        """Pair ``i``'s ``role`` video as ReCamMaster's cached dict: ``latents`` (16, T', 60, 104)
        bf16, ``prompt_emb`` ``{"context": (1, L, D)}`` bf16, ``image_emb`` ``{}``."""
        from paradrive.wan.vae import encode_video

        if self.cache is not None:   # causal in time: the first T' latent frames are those of the first frames
            latents = self.cache[i][f"{role}_latents"][:, :self.latent_frames]
            self.from_cache += 1
        else:
            if self.vae is None or self.text is None:
                raise ValueError("the cached tensors need a VAE and the empty prompt's embedding: pass --vae")
            if self.pixels is None:
                self.pixels = PairDataset(self.build, dtype="uint8", num_frames=self.frames,
                                          output_size=RECAMMASTER_SIZE, resize="crop")
            video = to_channels_first(frames_on(self.pixels[i][role][None], self.vae.device))
            latents = encode_video(self.vae, video)[0]
            self.encoded += 1
        assert self.text is not None
        return {"latents": latents.to(torch.bfloat16).cpu(),
                "prompt_emb": {"context": self.text[None].to(torch.bfloat16).cpu()}, "image_emb": {}}


def to_recammaster(build: str | Path, out: str | Path, latents: RecamLatents | None = None,
                   limit: int | None = None) -> dict[str, int]:
    """Write ReCamMaster's layout for every pair (the first ``limit``; see the module
    docstring); with ``latents`` also the cached ``.tensors.pth``, each distinct video's written
    once under ``OUT/latents/`` and hard-linked as every pair's ``cam01`` (the source; ``cam03`` …
    ``cam10`` too, the condition cameras ReCamMaster's loader may draw) and ``cam02`` (the
    target). Returns the counts: pairs, videos (distinct), encoded, from_cache, bytes (of the
    distinct files)."""
    ds = PairDataset(build, dtype="uint8")
    out = Path(out)
    names, written = [], {}
    for i, pair_id, row, folder in _pair_folders(ds, out / "train", build, limit):
        videos = {SOURCE_CAMERA: _video(ds, row, "source"), TARGET_CAMERA: _video(ds, row, "target")}
        for cam, src in videos.items():
            _place(src, folder / "videos" / f"{cam}.mp4")
        target_c2w, source_c2w = _pair_c2w(row)
        write_json(folder / "cameras" / "camera_extrinsics.json", recammaster_extrinsics(target_c2w, source_c2w))
        if latents is not None:
            for cams, role in (([SOURCE_CAMERA, *_CONDITION_CAMERAS], "source"), ([TARGET_CAMERA], "target")):
                sha = str(row[f"{role}_sha256"])
                if sha not in written:
                    written[sha] = out / LATENTS_FOLDER / f"{sha}.tensors.pth"
                    with atomic_path(written[sha]) as tmp:
                        torch.save(latents.tensors(i, role), tmp)
                for cam in cams:
                    _place(written[sha], folder / "videos" / f"{cam}.mp4.tensors.pth")
        names.append(f"{pair_id}/videos/{TARGET_CAMERA}.mp4")
    _write_csv(out / "metadata.csv", ["file_name", "text"], [{"file_name": n, "text": EMPTY_PROMPT} for n in names])
    return {"pairs": len(names), "videos": len(written),
            "encoded": latents.encoded if latents else 0, "from_cache": latents.from_cache if latents else 0,
            "bytes": sum(p.stat().st_size for p in written.values())}


# -- DiffSynth-Studio -------------------------------------------------------------------------------
def to_diffsynth(build: str | Path, out: str | Path, limit: int | None = None) -> int:
    """Write DiffSynth-Studio's ``metadata.csv`` / ``metadata.json`` and the videos they name
    for every pair (the first ``limit``; see the module docstring). Returns the number of pairs."""
    ds = PairDataset(build, dtype="uint8")
    out = Path(out)
    rows = []
    for _, pair_id, row, folder in _pair_folders(ds, out / "videos", build, limit):
        paths = {}
        for role in ("target", "source", "condition"):
            _place(_video(ds, row, role), folder / f"{role}.mp4")
            paths[role] = f"videos/{pair_id}/{role}.mp4"
        rel = torch.from_numpy(np.array(row["rel_pose"], dtype=np.float32))[None]
        camera = relative_camera(rel)[0].tolist()
        rows.append({"video": paths["target"], "prompt": EMPTY_PROMPT, "source_video": paths["source"],
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
    from safetensors.torch import save

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
            # written by Python, so a failed write (a full disk, a size limit) is the OSError it is
            tmp.write_bytes(save(tensors, metadata={"pair_id": pair_id, "offset_m": repr(sample["offset_m"])}))
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


def check_output(out: Path) -> None:
    """ValueError before any work when ``out`` cannot become the export: a file or device, a path
    under a file, a folder this user cannot write in, or a folder holding anything but an earlier
    export."""
    if out.is_dir():
        if any(out.iterdir()) and not (out / MARKER).is_file():
            raise ValueError(f"OUT {out} is a folder holding other files (no {MARKER}: not an earlier export); "
                             f"pass a new or empty folder")
    elif out.exists():
        raise ValueError(f"OUT {out} is a file, not a folder; pass the path of a folder to create")
    above = next(p for p in out.absolute().parents if p.exists())   # the export is made beside OUT
    if not above.is_dir():
        raise ValueError(f"OUT {out}: {above} is a file, not a folder; pass the path of a folder to create")
    if not os.access(above, os.W_OK | os.X_OK):
        raise ValueError(f"OUT {out}: {above} cannot be written by this user; pass another OUT")


def convert_build(fmt: str, build: Path, out: Path, *, vae: Path | str | None = None,
                  text_encoder: Path | None = None, num_frames: int | None = None,
                  size: tuple[int, int] | None = None, limit: int | None = None,
                  device: str | None = None, notes: list[str] | None = None) -> dict[str, int]:
    """Write ``build`` into ``out`` in the layout ``fmt`` names (one of :data:`FORMATS`), whole
    or not at all; its counts (``pairs``; for recammaster also ``videos``, ``encoded``,
    ``from_cache``, ``bytes``). ``device``: where the VAE and text encoder run (default: the
    encode stage's ``device``). ``notes``: what a user should know (a latent cache not used, and
    why). Usage errors (ValueError, FileNotFoundError, ConfigError) come before any work."""
    if fmt not in FORMATS:
        raise ValueError(f"format {fmt!r}: use one of {', '.join(FORMATS)}")
    if not build.is_dir():
        raise FileNotFoundError(f"{build}: no such build folder (run 'paradrive build' first)")
    if fmt == "diffsynth" and (size is not None or num_frames is not None):
        raise ValueError("convert diffsynth hands over the build's own videos: --size and --num-frames are for "
                         "recammaster and pixels")
    check_output(out)
    latents = None
    if fmt == "recammaster":
        check_recammaster_size(size)
        latents = recammaster_latents(build, recammaster_frames(build, num_frames), vae, text_encoder, device,
                                      notes if notes is not None else [])
    with atomic_path(out) as tmp:
        tmp.mkdir(parents=True)
        if fmt == "diffsynth":
            counts = {"pairs": to_diffsynth(build, tmp, limit)}
        elif fmt == "pixels":
            counts = {"pairs": to_pixels(build, tmp, num_frames=num_frames, output_size=size, limit=limit)}
        else:
            counts = to_recammaster(build, tmp, latents, limit)
        write_json(tmp / MARKER, {"format": fmt, "build": str(build), **counts})
    return counts


def recammaster_latents(build: Path, frames: int, vae: Path | str | None, text_encoder: Path | None,
                        device: str | None, notes: list[str]) -> RecamLatents:
    """Where the export's latents come from: the build's encode cache when it fits (then no VAE
    is loaded), else the VAE (``vae``, with umT5 from ``text_encoder`` or the VAE's folder), on
    ``device`` in the encode stage's compute dtype. ValueError when neither is there."""
    from paradrive.devices import resolve_device
    from paradrive.contracts.specs import StageRegistry
    from paradrive.wan.text import empty_prompt_embedding, tiny_text_embedding
    from paradrive.wan.vae import TINY, TINY_SEED, load_vae

    why = _cache_misfit(build, frames, vae)
    if why is None:
        return RecamLatents(build, frames, cache=PairDataset(build, latents=True, dtype="bfloat16"))
    if vae is None:
        raise ValueError(f"convert recammaster needs --vae DIR (its text_encoder/ too, or --text-encoder DIR), "
                         f"or a latent cache of the build that fits (its {why}): ReCamMaster's data_process "
                         f"caches only the videos metadata.csv lists (each pair's cam02, the target) and its "
                         f"loader then fails on every cam01 (the source) it needs beside it, retrying forever; "
                         f"with --vae both videos' <video>.tensors.pth are written here")
    if has_latents(build):
        notes.append(f"the build's latent cache is not used: its {why}; encoding with --vae {vae}")
    settings = StageRegistry().resolve(None, {"encode": {"device": device} if device else {}}).typed("encode")
    dtype = {"float32": torch.float32, "bfloat16": torch.bfloat16}[settings.compute_dtype]
    where = resolve_device(settings.device)
    text = text_encoder or vae   # as paradrive encode: a Wan2.1 folder holds both
    if str(text) == TINY:
        from paradrive.wan.recam import tiny_transformer_config

        embedding = tiny_text_embedding(TINY_SEED, int(tiny_transformer_config()["text_dim"]))
    else:
        embedding = empty_prompt_embedding(text, where, dtype)
    return RecamLatents(build, frames, load_vae(vae, where, dtype), embedding)


def _cache_misfit(build: Path, frames: int, vae: Path | str | None) -> str | None:
    """Why the build's latent cache cannot serve a ReCamMaster export of ``frames`` frames (as
    what follows "its" in a sentence), None when it can."""
    from paradrive.errors import ParaDriveError
    from paradrive.latents import read_latents_index
    from paradrive.wan.vae import vae_checksum

    if not has_latents(build):
        return "latent cache is missing (paradrive encode BUILD --vae DIR makes one)"
    try:
        doc = read_latents_index(build)
    except ParaDriveError as exc:
        return f"latent cache cannot be read ({exc})"
    differ = []
    if list(doc["size"]) != list(RECAMMASTER_SIZE) or doc["resize"] != "crop":
        differ.append(f"frames were encoded at {doc['size'][0]}x{doc['size'][1]} ({doc['resize']}), ReCamMaster "
                      f"reads 480x832 (crop)")
    if int(doc["num_frames"]) < frames:
        differ.append(f"videos were encoded at {doc['num_frames']} frames, the export needs {frames}")
    if vae is not None and vae_checksum(vae) != doc["vae"]["sha256"]:
        differ.append(f"VAE was {doc['vae']['path']}, not --vae {vae}")
    return "; ".join(differ) or None
