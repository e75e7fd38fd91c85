"""Pair shards are checked against their sha256 in ``index.json`` as they are read: a byte
flipped in a published shard (its size and modification time set back, so only its bytes tell)
is one error naming the shard, the build and the fix in the adapter, the trainers, the latent
encode and convert, instead of rows with wrong values. A healthy build reads, hashing each shard
once per process. And a resume state is refused by any rank but the one that saved it."""

from __future__ import annotations

import json
import os
import pickle
import shutil
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from paradrive import pairs
from paradrive.data import PairDataset, PairIterableDataset
from paradrive.errors import ParaDriveError
from paradrive.pairs import ShardChecksumError, read_pairs


@pytest.fixture
def build(smoke_build, tmp_path) -> Path:
    """A copy of the smoke build, as ``<manifests>/smoke``, to damage."""
    dst = tmp_path / "manifests" / "smoke"
    shutil.copytree(smoke_build["build_dir"], dst, symlinks=True)
    return dst


def first_shard(build: Path) -> tuple[Path, str]:
    """The first shard's path and its name relative to the build (``v-<n>/pairs-00000.parquet``)."""
    doc = json.loads((build / "index.json").read_text())
    rel = f"{doc['version']}/{doc['shards'][0]['file']}"
    return build / rel, rel


def _intrinsics(data: bytes) -> list | None:
    try:
        return pq.ParquetFile(pa.BufferReader(data)).read(columns=["intrinsics"]).column(0).to_pylist()
    except (pa.ArrowException, OSError):
        return None


def flip_a_byte(shard: Path) -> None:
    """Flip one bit of the shard's ``intrinsics`` column so the file still reads as Parquet and
    a value is wrong; its size and modification time are set back."""
    data = shard.read_bytes()
    column = pq.ParquetFile(shard).metadata.row_group(0).column(
        pq.read_schema(shard).get_field_index("intrinsics"))
    start = column.dictionary_page_offset or column.data_page_offset
    healthy = _intrinsics(data)
    offset = next(off for off in range(start, start + column.total_compressed_size)
                  if _intrinsics(data[:off] + bytes([data[off] ^ 1]) + data[off + 1:]) not in (None, healthy))
    before = shard.stat()
    with open(shard, "r+b") as f:
        f.seek(offset)
        f.write(bytes([data[offset] ^ 1]))
    os.utime(shard, ns=(before.st_atime_ns, before.st_mtime_ns))
    after = shard.stat()
    assert (after.st_size, after.st_mtime_ns) == (before.st_size, before.st_mtime_ns)
    assert shard.read_bytes() != data


def assert_the_one_line_error(error: pytest.ExceptionInfo, build: Path, rel: str) -> None:
    message = str(error.value)
    assert isinstance(error.value, ParaDriveError) and "\n" not in message
    assert message.startswith(f"build {build}: shard {rel} does not match its sha256 in index.json")
    assert message.endswith(f"run paradrive build --manifests {build.parent} --build smoke again to heal it")


@pytest.fixture
def hashes(monkeypatch) -> list[Path]:
    """Every shard hashed from now on; the process's record of hashed shards starts empty, as in
    a new process."""
    hashed: list[Path] = []
    real = pairs._sha256

    def counting(path: Path, *args) -> str:
        hashed.append(Path(path))
        return real(path, *args)

    monkeypatch.setattr(pairs, "_sha256", counting)
    monkeypatch.setattr(pairs, "_MATCHED", {})
    return hashed


# --------------------------------------------------------------------------- a healthy build

@pytest.mark.slow
def test_a_healthy_build_reads_and_each_shard_is_hashed_once_per_process(build, hashes, monkeypatch):
    shards = pairs.shard_paths(build)
    ds = PairDataset(build, dtype="uint8", num_frames=2)
    assert sorted(hashes) == sorted(shards)   # every shard, once, when the build is opened
    sample = ds[len(ds) - 1]
    assert sample["source"].shape[0] == 2 and sample["intrinsics"].shape == (4,)
    rows = [ds.row(i)["pair_id"] for i in range(len(ds))]
    assert rows == ds.pair_ids
    PairDataset(build)                        # opened again in this process: its stat is the same
    PairIterableDataset(build, rank=1, world_size=2)
    read_pairs(build, ["pair_id"], verify=True)
    assert sorted(hashes) == sorted(shards)   # nothing hashed since, whatever was read
    worker = pickle.loads(pickle.dumps(ds))   # as a DataLoader hands it to a worker process
    monkeypatch.setattr(pairs, "_MATCHED", {})
    assert [worker.row(i)["pair_id"] for i in range(len(worker))] == rows
    assert sorted(hashes) == sorted(shards)   # the worker trusts the stat it was opened with


def test_verify_shards_takes_true_or_false(tmp_path):
    with pytest.raises(ValueError, match=r"^PairDataset\(verify_shards='no'\): must be True or False$"):
        PairDataset(tmp_path, verify_shards="no")


# --------------------------------------------------------------------------- a flipped byte

@pytest.mark.slow
def test_a_flipped_byte_is_one_error_naming_the_shard_the_build_and_the_fix(build):
    shard, rel = first_shard(build)
    healthy = PairDataset(build).row(0)["intrinsics"]   # hashed once before the damage
    flip_a_byte(shard)
    # without the check the rows read, with a wrong value in them
    assert PairDataset(build, verify_shards=False).row(0)["intrinsics"] != healthy
    with pytest.raises(ShardChecksumError) as error:
        PairDataset(build)
    assert_the_one_line_error(error, build, rel)
    with pytest.raises(ShardChecksumError) as error:
        PairIterableDataset(build, seed=0, num_frames=2)
    assert_the_one_line_error(error, build, rel)
    with pytest.raises(ShardChecksumError) as error:
        PairDataset(build, latents=True)
    assert_the_one_line_error(error, build, rel)
    with pytest.raises(ShardChecksumError) as error:
        read_pairs(build, verify=True)
    assert_the_one_line_error(error, build, rel)


@pytest.mark.slow
def test_a_shard_flipped_after_the_open_is_refused_where_a_worker_opens_it(build, hashes, monkeypatch):
    ds = PairDataset(build, dtype="uint8", num_frames=2)
    worker = pickle.loads(pickle.dumps(ds))
    shard, rel = first_shard(build)
    flip_a_byte(shard)
    monkeypatch.setattr(pairs, "_MATCHED", {})   # the worker's own process
    with pytest.raises(ShardChecksumError) as error:
        worker.row(0)
    assert_the_one_line_error(error, build, rel)
    with pytest.raises(ShardChecksumError):
        ds.row(0)                                 # its first read of the shard comes after the flip


@pytest.mark.slow
def test_the_trainers_and_convert_refuse_a_flipped_shard(build, tmp_path):
    from paradrive.train.convert import convert_build
    from paradrive.train.trainer import open_dataset

    shard, rel = first_shard(build)
    flip_a_byte(shard)
    data = {"num_frames": 2, "frame_stride": 1, "height": 48, "width": 64}
    with pytest.raises(ShardChecksumError) as error:
        open_dataset(build, {"data": data})
    assert_the_one_line_error(error, build, rel)
    out = tmp_path / "pixels"
    with pytest.raises(ShardChecksumError) as error:
        convert_build("pixels", build, out, num_frames=2)
    assert_the_one_line_error(error, build, rel)
    assert not out.exists()


@pytest.mark.slow
def test_the_latent_encode_refuses_a_flipped_shard_before_writing(build, wan_folder):
    pytest.importorskip("diffusers")
    from paradrive.latents import latents_index_path
    from paradrive.wan.encode import EncodeSettings, encode_build

    shard, rel = first_shard(build)
    flip_a_byte(shard)
    settings = EncodeSettings(vae=str(wan_folder), text_encoder=None, device="cpu", dtype="bfloat16",
                              compute_dtype="float32", batch=4, shard_pairs=20, num_frames=None,
                              size=(24, 40), resize="crop")
    with pytest.raises(ShardChecksumError) as error:
        encode_build(build, settings)
    assert_the_one_line_error(error, build, rel)
    assert not latents_index_path(build).exists()


@pytest.mark.slow
def test_a_missing_shard_is_named_in_one_line(build):
    shard, _ = first_shard(build)
    shard.unlink()
    with pytest.raises(ParaDriveError, match=rf"^{shard} is listed in {build / 'index.json'} but missing; re-run"):
        PairDataset(build)


# --------------------------------------------------------------------------- resume by rank

@pytest.mark.slow
def test_a_state_is_loaded_only_by_the_rank_and_world_size_that_saved_it(smoke_build):
    build = smoke_build["build_dir"]
    saved = PairIterableDataset(build, rank=1, world_size=2, seed=3).state_dict(samples_consumed=5)
    with pytest.raises(ValueError) as error:
        PairIterableDataset(build, rank=0, world_size=2, seed=3).load_state_dict(saved)
    assert str(error.value) == (
        "cannot resume: the state was saved by rank 1 of world_size 2, and rank 0 of world_size 2 "
        "is loading it; load each rank's own state_dict() with the same world_size, or start a new epoch")
    with pytest.raises(ValueError, match=r"saved by rank 1 of world_size 2, and rank 1 of world_size 4 is loading"):
        PairIterableDataset(build, rank=1, world_size=4, seed=3).load_state_dict(saved)
    same = PairIterableDataset(build, rank=1, world_size=2, seed=3)
    same.load_state_dict(saved)
    assert same.state_dict(samples_consumed=0)["samples_consumed"] == 5
    assert list(same.worker_order()) == list(same.rank_order()[5:])


def test_a_plain_build_heals_a_flipped_shard_whose_time_was_set_back(smoke_build, copy_tree):
    import subprocess
    import sys

    root = copy_tree(smoke_build["root"], "root")
    build = root / "manifests" / "smoke"
    shard, rel = first_shard(build)
    healthy = read_pairs(build, verify=True)
    flip_a_byte(shard)
    with pytest.raises(ShardChecksumError) as error:
        PairDataset(build)
    assert_the_one_line_error(error, build, rel)
    scenes = [arg for uri in smoke_build["scene_uris"] for arg in ("--scene", uri)]
    rerun = subprocess.run([sys.executable, "-m", "paradrive.cli", "build", *scenes, "--profile", "smoke",
                            "--data", str(root / "data"), "--manifests", str(root / "manifests"),
                            "--build", "smoke"], capture_output=True, text=True,
                           env={**os.environ, "COLUMNS": "250"})
    assert rerun.returncode == 0, rerun.stdout[-3000:] + rerun.stderr[-3000:]
    assert "done manifest" in rerun.stderr   # found damaged: published again, not skipped
    assert read_pairs(build, verify=True).equals(healthy)   # the rows before the flip
