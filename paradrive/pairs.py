"""The published pair format: the Parquet schema of a row, pair ids, and reading a build
(``<manifests>/<build>/index.json`` + ``pairs-*.parquet`` + ``media/``) safely.

Written by the manifest stage (:mod:`paradrive.manifest`), read by the dataset adapter, inspect,
eval and the inference scorer. Every URI a row or the index holds is checked to stay inside the
build folder before it is opened.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
from pydantic import ValidationError

from paradrive.errors import ParaDriveError, validation_message
from paradrive.io import check_relative, path_inside
from paradrive.contracts.layout import INDEX_JSON, MEDIA_DIR, BuildLayout
from paradrive.contracts.records import IndexRecord
from paradrive.streams import format_offset

SCHEMA_VERSION = 1
INDEX_FORMAT = "paradrive-pairs"
media_uri = BuildLayout.media_uri

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


def make_pair_id(dataset: str, scene_id: str, camera: str, clip: str, offset_m: float,
                 condition_iteration: int) -> str:
    """``<dataset>/<scene_id>/<camera>/<clip>/<+2m>/<000500>``: stable across builds."""
    return (f"{dataset}/{scene_id}/{camera}/{clip}/{format_offset(offset_m)}/"
            f"{int(condition_iteration):06d}")


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


def build_file(build_dir: str | Path, uri: object, what: str, index: IndexRecord) -> Path:
    """The file a build-relative ``uri`` names, checked to stay inside the build.

    A build published with ``media: symlink`` links each media file to the scene's own clip in
    the data folder: such a link may lead out, but only to ``<...>/<scene_id>/<file>`` named
    like the URI, never to an arbitrary file.
    """
    linked = index.media.mode == "symlink"
    tail = Path(str(uri)).parts[1:] if str(uri).startswith(MEDIA_DIR + "/") else ()

    def scene_clip(resolved: Path) -> bool:
        return linked and len(tail) >= 2 and resolved.parts[-len(tail):] == tail

    return path_inside(build_dir, uri, what, may_lead_out=scene_clip)


# --------------------------------------------------------------------------- reading

def read_index(build_dir: str | Path) -> IndexRecord:
    """The build's ``index.json``; a clear error when the folder holds no published build."""
    build_dir = Path(build_dir)
    path = build_dir / INDEX_JSON
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
    if not isinstance(index, dict) or index.get("format") != INDEX_FORMAT:
        raise ParaDriveError(f"{path} is not a paradrive pair index (format "
                             f"{index.get('format') if isinstance(index, dict) else None!r})")
    if index.get("schema_version") != SCHEMA_VERSION:
        raise ParaDriveError(f"{path}: manifest schema_version {index.get('schema_version')!r} "
                             f"is not {SCHEMA_VERSION}; rebuild it with this paradrive version")
    try:
        return IndexRecord.model_validate(index)
    except ValidationError as exc:
        raise ParaDriveError(f"{path}: {validation_message(exc)}; re-run the manifest stage "
                             f"(paradrive build --stages manifest --force)") from exc


def shard_paths(build_dir: str | Path, index: IndexRecord | None = None) -> list[Path]:
    build_dir = Path(build_dir)
    index = index or read_index(build_dir)
    return [path_inside(build_dir, s.file, f"{build_dir / INDEX_JSON}: shard {k}")
            for k, s in enumerate(index.shards)]


def read_pairs(build_dir: str | Path, columns: Iterable[str] | None = None) -> pa.Table:
    """Every row of a build (the shards its index lists, in order) as one Arrow table."""
    build_dir = Path(build_dir)
    paths = shard_paths(build_dir)
    tables = []
    for p in paths:
        if not p.is_file():
            raise ParaDriveError(f"{p} is listed in {build_dir / INDEX_JSON} but missing; "
                                 f"re-run the manifest stage (paradrive build --stages manifest "
                                 f"--force)")
        tables.append(pq.read_table(p, columns=list(columns) if columns else None))
    return pa.concat_tables(tables) if tables else SCHEMA.empty_table()
