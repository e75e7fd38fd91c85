"""The published pair format: the Parquet schema of a row, pair ids, and reading a build
(``<manifests>/<build>/index.json`` naming a version folder ``v-<nnnnnn>/`` with
``pairs-*.parquet`` + ``media/``) safely.

Written by the manifest stage (:mod:`paradrive.manifest`), read by the dataset adapter, inspect,
eval and the inference scorer. Readers read ``index.json`` once and open only the version it
names, so a build republished meanwhile is never seen half old, half new; a publish keeps the
versions readers may still hold (``manifest.keep_versions_for``), so they read them to the end.
Every URI a row or the index holds is checked to stay inside that version folder before it is
opened, and a reader that trains on the rows (the adapter, the latent encode) checks each shard's
sha256 against the index when it opens it (:func:`check_shards`), once per process while the
file's stat stays the same.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
from pydantic import ValidationError

from paradrive.errors import ConfigError, ParaDriveError, validation_message
from paradrive.io import PathEscapeError, check_relative, path_inside
from paradrive.contracts.layout import INDEX_JSON, MEDIA_DIR, SCENES_DIR, BuildLayout
from paradrive.contracts.records import IndexRecord, ShardRecord
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
    ("dynamic_fraction", pa.float64()),
])

COLUMNS = tuple(SCHEMA.names)


def make_pair_id(dataset: str, scene_id: str, camera: str, clip: str, offset_m: float,
                 condition_iteration: int) -> str:
    """``<dataset>/<scene_id>/<camera>/<clip>/<+2m>/<000500>``: stable across builds."""
    return (f"{dataset}/{scene_id}/{camera}/{clip}/{format_offset(offset_m)}/"
            f"{int(condition_iteration):06d}")


URI_COLUMNS = ("source_uri", "condition_uri", "target_uri")
# the scene files a symlink build's media may link to: clips/<camera>/<clip>/<stream>.<mp4|mkv>
CLIP_FILE = re.compile(r"clips/[^/]+/[^/]+/[^/]+\.(?:mp4|mkv)")


def check_row_uris(columns: dict, where: str) -> None:
    """Every URI of ``columns`` ({pair_id: [...], source_uri: [...], ...}) is a relative,
    normalised path inside the build; else a PathEscapeError naming ``where``, the row and column."""
    checked: set = set()  # rows share videos: a target serves every offset and checkpoint
    for column in URI_COLUMNS:
        for pair_id, uri in zip(columns["pair_id"], columns[column]):
            if uri is not None and uri not in checked:  # an inference row may have no target
                check_relative(uri, f"{where}: row {pair_id} column {column}")
                checked.add(uri)


def version_dir(build_dir: str | Path, index: IndexRecord) -> Path:
    """The folder ``index``'s shards and URIs are relative to: the version it names."""
    layout = BuildLayout(Path(build_dir))
    try:
        return layout.version(index.version) if index.version is not None else layout.root
    except ConfigError as exc:
        raise PathEscapeError(str(exc)) from exc


_SCENE_IDS: list[tuple[IndexRecord, frozenset[str]]] = []


def _scene_ids(index: IndexRecord) -> frozenset[str]:
    """The scene ids ``index`` lists, gathered once per index: every media file of a symlink
    build is checked against them, and gathering them per file made verifying a build quadratic
    in its scenes."""
    if not _SCENE_IDS or _SCENE_IDS[0][0] is not index:
        _SCENE_IDS[:] = [(index, frozenset(s.scene_id for s in index.scenes))]
    return _SCENE_IDS[0][1]


def _linked_clip(index: IndexRecord, uri: str) -> Path | None:
    """Where a ``symlink`` build's media link for ``uri`` must lead: the clip file of one of the
    build's own scenes, inside the data folder it was published from; None for anything else."""
    root = index.media.data_root
    parts = uri.split("/")
    if index.media.mode != "symlink" or not root or len(parts) < 3 or parts[0] != MEDIA_DIR:
        return None
    scene_id, file = parts[1], "/".join(parts[2:])
    if scene_id not in _scene_ids(index) or not CLIP_FILE.fullmatch(file):
        return None
    return Path(root) / SCENES_DIR / scene_id / file


def build_file(build_dir: str | Path, uri: object, what: str, index: IndexRecord) -> Path:
    """The file a version-relative ``uri`` names, checked to stay inside the build version.

    A build published with ``media: symlink`` links each media file to the scene's own clip in
    the data folder: such a link may lead out, but only to exactly that clip file
    (``<data_root>/scenes/<scene_id>/clips/<camera>/<clip>/<stream>.<mp4|mkv>`` of a scene the
    index lists), never to an arbitrary file.
    """
    expected = _linked_clip(index, uri) if isinstance(uri, str) else None

    def scene_clip(resolved: Path) -> bool:
        return expected is not None and resolved == expected.resolve()

    return path_inside(version_dir(build_dir, index), uri, what, may_lead_out=scene_clip)


# --------------------------------------------------------------------------- reading

def read_index(build_dir: str | Path, version: str | None = None) -> IndexRecord:
    """The build's ``index.json`` (the version it names now), or with ``version`` the index of
    that version while a publish keeps it; a clear error when there is none."""
    build_dir = Path(build_dir)
    path = build_dir / INDEX_JSON
    if not build_dir.is_dir():
        raise ParaDriveError(f"build folder {build_dir} does not exist; pass the folder "
                             f"<manifests>/<build> that `paradrive build` wrote")
    if version is not None:
        return _version_index(build_dir, version)
    if not path.is_file():
        raise ParaDriveError(f"{path} is missing: the build was never published here; run "
                             f"`paradrive build` (a build being published keeps its last index)")
    return _parse_index(path)


def _version_index(build_dir: Path, version: str) -> IndexRecord:
    try:
        path = BuildLayout(build_dir).version_index(version)
    except ConfigError as exc:
        raise ParaDriveError(str(exc)) from exc
    if not path.is_file():
        raise ParaDriveError(f"build {build_dir}: version {version} is no longer kept (a publish "
                             f"keeps the version it replaces and those replaced less than "
                             f"manifest.keep_versions_for ago); open the build's current version "
                             f"({current_version(build_dir)}) at the next epoch")
    index = _parse_index(path)
    if index.version != version:
        raise ParaDriveError(f"{path} names version {index.version!r}, not {version}; re-run the "
                             f"manifest stage (paradrive build --stages manifest --force)")
    return index


def current_version(build_dir: str | Path) -> str | None:
    """The version ``index.json`` names now (None when it is missing or unreadable): what a
    trainer compares with the version it reads, at an epoch boundary, to pick up a republish."""
    try:
        return read_index(build_dir).version
    except ParaDriveError:
        return None


def _parse_index(path: Path) -> IndexRecord:
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
    folder = version_dir(build_dir, index)
    return [path_inside(folder, s.file, f"{build_dir / INDEX_JSON}: shard {k}")
            for k, s in enumerate(index.shards)]


def read_shard(path: Path, columns: Iterable[str] | None = None) -> pa.Table:
    """One shard; a truncated or damaged file is a one-line error naming it. Read through
    ``ParquetFile``: ``pq.read_table`` goes through ``pyarrow.dataset``, which imports pandas
    (about a second, and tens of MB, in every process that opens a build)."""
    try:
        with pq.ParquetFile(path) as shard:
            return shard.read(columns=list(columns) if columns else None)
    except (pa.ArrowException, OSError) as exc:
        raise _corrupt_shard(path, exc) from exc


def iter_shard(path: Path, columns: Iterable[str], batch_rows: int = 4096) -> Iterator[pa.RecordBatch]:
    """A shard's rows ``batch_rows`` at a time, so a reader of every row of a build holds one
    batch, not the build; errors as :func:`read_shard`'s."""
    try:
        with pq.ParquetFile(path) as shard:
            yield from shard.iter_batches(batch_size=batch_rows, columns=list(columns))
    except (pa.ArrowException, OSError) as exc:
        raise _corrupt_shard(path, exc) from exc


def _corrupt_shard(path: Path, exc: BaseException) -> ParaDriveError:
    first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
    return ParaDriveError(f"corrupt: {path} cannot be read as Parquet ({first}); re-run the "
                          f"build without --stages (the same paradrive build command) to "
                          f"publish it again")


def read_pairs(build_dir: str | Path, columns: Iterable[str] | None = None,
               index: IndexRecord | None = None, *, verify: bool = False) -> pa.Table:
    """Every row of a build (the shards its index lists, in order) as one Arrow table.

    ``index``: the one the caller read (and resolves media through); without it, ``index.json``
    is read here. A caller that reads the index and the rows apart must pass it, or a republish
    between the two reads gives it rows of one version and media of another. ``verify``: check
    each shard's sha256 against the index first (:func:`check_shards`), as a reader that trains
    or encodes on the rows must; a summary that re-hashes them itself leaves it off."""
    build_dir = Path(build_dir)
    index = index or read_index(build_dir)
    paths = shard_paths(build_dir, index)
    if verify:
        check_shards(build_dir, index, paths)
    tables = []
    for p in paths:
        _check_listed(build_dir, p)
        tables.append(read_shard(p, columns))
    return pa.concat_tables(tables) if tables else SCHEMA.empty_table()


def _check_listed(build_dir: Path, path: Path) -> None:
    if not path.is_file():
        raise ParaDriveError(f"{path} is listed in {build_dir / INDEX_JSON} but missing; "
                             f"re-run the manifest stage (paradrive build --stages manifest "
                             f"--force)")


# --------------------------------------------------------------------------- shard checksums

class ShardChecksumError(ParaDriveError):
    """A published shard whose bytes are not those ``index.json`` lists (a flipped byte keeps
    the Parquet readable and its values wrong); a plain ``paradrive build`` publishes it again."""


# A shard's stamp: its path and the stat of the bytes that were hashed. Any write to the file
# changes its ctime, which (unlike its mtime) a program cannot set back, so while the stamp is
# the same the bytes are the ones hashed.
ShardStamp = tuple[str, int, int, int, int, int]
_MATCHED: dict[ShardStamp, str] = {}   # stamp -> the sha256 its bytes had, in this process


def shard_stamp(path: Path) -> ShardStamp:
    st = os.stat(path)
    return (str(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def check_shards(build_dir: str | Path, index: IndexRecord,
                 paths: Sequence[Path] | None = None) -> list[ShardStamp]:
    """Check that every shard of ``index`` has the sha256 the index lists; returns their stamps.

    A shard is hashed once per process while its stat stays the same (its stamp); those not yet
    hashed are hashed at once on up to as many threads as the CPUs (hashlib lets go of the GIL).
    A missing shard, or one whose bytes differ, raises one error naming the shard, the build and
    the fix (:class:`ShardChecksumError` for the bytes)."""
    build_dir = Path(build_dir)
    paths = list(paths) if paths is not None else shard_paths(build_dir, index)
    return _check(build_dir, index, list(index.shards), paths)


def check_shard_again(build_dir: str | Path, index: IndexRecord, k: int, path: Path,
                      stamp: ShardStamp) -> None:
    """Shard ``k``, checked by :func:`check_shards` with ``stamp``, re-checked as a reader opens
    it later (a DataLoader worker, or after the file was touched): a stat while the stamp is the
    same, its sha256 again otherwise."""
    if not path.is_file() or shard_stamp(path) != stamp:
        _check(Path(build_dir), index, [index.shards[k]], [path])


def _check(build_dir: Path, index: IndexRecord, entries: list[ShardRecord],
           paths: list[Path]) -> list[ShardStamp]:
    for path in paths:
        _check_listed(build_dir, path)
    stamps = [shard_stamp(path) for path in paths]
    todo = [k for k, stamp in enumerate(stamps) if stamp not in _MATCHED]
    jobs = min(len(todo), _cpus(), 8)
    if jobs > 1:
        with ThreadPoolExecutor(jobs) as pool:
            found = list(pool.map(lambda k: _sha256(paths[k]), todo))
    else:
        found = [_sha256(paths[k]) for k in todo]
    for k, sha in zip(todo, found):
        _MATCHED[stamps[k]] = sha
    for entry, stamp in zip(entries, stamps):
        if _MATCHED[stamp] != entry.sha256:
            raise shard_mismatch(build_dir, index, entry, _MATCHED[stamp])
    return stamps


def _sha256(path: Path, chunk: int = 1 << 18) -> str:
    """The file's sha256, read into one buffer of ``chunk`` bytes: opening a build allocates
    a quarter of a MB a hashing thread, not a new block per read."""
    h, buffer = hashlib.sha256(), bytearray(chunk)
    view = memoryview(buffer)
    with open(path, "rb", buffering=0) as f:
        while n := f.readinto(buffer):
            h.update(view[:n])
    return h.hexdigest()


def _cpus() -> int:
    affinity = getattr(os, "sched_getaffinity", None)
    return len(affinity(0)) if affinity else os.cpu_count() or 1


def shard_mismatch(build_dir: Path, index: IndexRecord, entry: ShardRecord, actual: str) -> ShardChecksumError:
    shard = f"{index.version}/{entry.file}" if index.version else entry.file
    return ShardChecksumError(
        f"build {build_dir}: shard {shard} does not match its sha256 in {INDEX_JSON} "
        f"({actual[:12]}… read, {entry.sha256[:12]}… listed); run paradrive build "
        f"--manifests {build_dir.parent} --build {build_dir.name} again to heal it")
