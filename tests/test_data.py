"""The trainer's adapter: decoding, sample contents and types, seeking, ranks x workers,
deterministic order, resume."""

from __future__ import annotations

import hashlib
import json
import re
import shutil

import numpy as np
import pytest

from conftest import stage_params
import torch
from torch.utils.data import DataLoader

from paradrive import geometry
from paradrive.data import (PairDataset, PairIterableDataset, output_geometry, recammaster_camera,
                            to_unit_range)
from paradrive.video import decode_frames, each_frame
from paradrive.errors import ParaDriveError
from paradrive.stages.manifest import build_manifest
from paradrive.pairs import read_index, read_pairs, version_dir
from test_manifest import frame_pixels, scenes_entry, write_clip_scene, write_video


def media(build, uri: str):
    """A row's video: URIs are relative to the version folder the build's index names."""
    return version_dir(build, read_index(build)) / uri


@pytest.fixture(scope="module")
def build(tmp_path_factory):
    """Two scenes x 72 pairs (3 clips x 8 offsets x 3 checkpoints), 8 frames of 64x48."""
    data = tmp_path_factory.mktemp("data")
    scenes = [write_clip_scene(data, "synthetic-a"), write_clip_scene(data, "synthetic-b")]
    build_dir = tmp_path_factory.mktemp("manifests") / "b"
    build_manifest(build_dir, [scenes_entry(s) for s in scenes], stage_params("manifest", {"shard_rows": 40,
                                                                  "row_group_rows": 8}))
    return build_dir


@pytest.fixture(scope="module")
def long_build(tmp_path_factory):
    """One clip of 121 frames of 32x32 with a keyframe every 30: one target, condition and source."""
    data = tmp_path_factory.mktemp("long")
    scene = write_clip_scene(data / "data", "synthetic-long", clips=("front",), offsets=(2.0,),
                             conditions=(100,), num_frames=121, width=32, height=32, gop=30)
    build_dir = data / "b"
    build_manifest(build_dir, [scenes_entry(scene)], stage_params("manifest", {}))
    return build_dir


@pytest.fixture(scope="module")
def long_video(tmp_path_factory):
    """40 frames of H.264 with B-frames and a keyframe every 5 frames."""
    import av

    path = tmp_path_factory.mktemp("video") / "long.mp4"
    frames = [frame_pixels(3, i, 64, 48) for i in range(40)]
    with av.open(str(path), "w") as out:
        s = out.add_stream("libx264", rate=10)
        s.width, s.height, s.pix_fmt = 64, 48, "yuv420p"
        s.options = {"crf": "10", "preset": "veryfast", "g": "5", "keyint_min": "5", "bf": "2"}
        for img in frames:
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                out.mux(p)
        for p in s.encode():
            out.mux(p)
    return path, frames


# --------------------------------------------------------------------------- decoding

def test_lossless_video_decodes_to_the_exact_frames_in_order(tmp_path):
    frames = [frame_pixels(5, i, 32, 24) for i in range(6)]
    path = tmp_path / "v.mkv"
    write_video(path, frames, codec="ffv1")
    np.testing.assert_array_equal(decode_frames(path), np.stack(frames))
    np.testing.assert_array_equal(decode_frames(path, [4, 1, 1]), np.stack(frames)[[4, 1, 1]])


def test_h264_frames_match_the_source_values_and_order(long_video):
    path, frames = long_video
    decoded = decode_frames(path)
    assert decoded.shape == (40, 48, 64, 3)
    assert np.abs(decoded.astype(int) - np.stack(frames).astype(int)).mean() < 3.0
    # Each decoded frame is nearest to its own source frame: the order survived.
    src = np.stack(frames).reshape(40, -1).astype(float)
    dist = ((decoded.reshape(40, -1)[:, None, :] - src[None]) ** 2).mean(axis=2)
    assert list(dist.argmin(axis=1)) == list(range(40))


def test_seeking_gives_the_same_frames_as_a_full_decode_and_decodes_fewer(long_video):
    path, _ = long_video
    full = decode_frames(path)
    for wanted in ([30], [7, 13, 14], [39], [0, 5, 10, 35], [22, 21]):
        stats = {}
        np.testing.assert_array_equal(decode_frames(path, wanted, stats=stats), full[wanted])
        assert stats["decoded"] <= max(wanted) - min(wanted) + 12  # from the keyframe before, not 0
    stats = {}
    decode_frames(path, [33], stats=stats)
    assert stats["decoded"] < 15


@pytest.mark.parametrize("codec", ["ffv1", "libx264"])
def test_planar_frames_are_the_interleaved_frames_channel_first(tmp_path, codec):
    frames = [frame_pixels(7, i, 32, 24) for i in range(5)]
    path = tmp_path / ("v.mkv" if codec == "ffv1" else "v.mp4")
    write_video(path, frames, codec=codec)
    interleaved = decode_frames(path)
    if codec == "ffv1":
        np.testing.assert_array_equal(interleaved, np.stack(frames))
    planar = {}
    each_frame(path, None, lambda i, planes: planar.setdefault(i, np.stack(planes)), planar=True)
    assert sorted(planar) == list(range(5))
    for i in range(5):
        np.testing.assert_array_equal(planar[i], interleaved[i].transpose(2, 0, 1))


def test_asking_past_the_end_names_the_file(long_video):
    path, _ = long_video
    with pytest.raises(ParaDriveError, match="long.mp4"):
        decode_frames(path, [38, 45])


# --------------------------------------------------------------------------- samples

def test_sample_has_the_trainer_keys_shapes_and_ranges(build):
    ds = PairDataset(build)
    assert len(ds) == 144
    s = ds[5]
    for role in ("source", "condition", "target"):
        assert s[role].shape == (8, 3, 48, 64) and s[role].dtype == torch.float32
        assert -1.0 <= s[role].min() and s[role].max() <= 1.0
    assert s["rel_pose"].shape == (8, 4, 4) and s["identity_pose"].shape == (8, 4, 4)
    assert torch.equal(s["identity_pose"], torch.eye(4).expand(8, 4, 4))
    row = read_pairs(build).slice(5, 1).to_pylist()[0]
    assert s["pair_id"] == row["pair_id"] and s["prompt"] == ""
    assert s["offset_m"] == row["offset_m"] and s["condition_iteration"] == row["condition_iteration"]
    np.testing.assert_allclose(s["rel_pose"].numpy().reshape(8, 16), np.asarray(row["rel_pose"]))
    np.testing.assert_allclose(s["intrinsics"].numpy(), row["intrinsics"])


def test_target_frames_are_the_video_frames_scaled_to_minus_one_one(build):
    ds = PairDataset(build, num_frames=3, frame_stride=2, frame_offset=1)
    s = ds[17]
    row = ds.row(17)
    video = decode_frames(media(build, row["target_uri"]))[[1, 3, 5]]
    expected = torch.from_numpy(video).permute(0, 3, 1, 2).float() / 127.5 - 1
    assert torch.equal(s["target"], expected)
    np.testing.assert_allclose(s["rel_pose"].numpy(), row["rel_pose"][[1, 3, 5]], atol=1e-7)


def test_uint8_samples_are_the_stored_frames_and_float_samples_their_normalisation(build):
    window = {"num_frames": 3, "frame_stride": 2, "frame_offset": 1}
    raw = PairDataset(build, dtype="uint8", **window)[17]
    row = PairDataset(build).row(17)
    for role in ("source", "condition", "target"):
        video = decode_frames(media(build, row[f"{role}_uri"]))[[1, 3, 5]]
        assert raw[role].dtype == torch.uint8 and raw[role].shape == (3, 3, 48, 64)
        assert torch.equal(raw[role], torch.from_numpy(video).permute(0, 3, 1, 2))
    for dtype in (torch.float32, torch.bfloat16):
        s = PairDataset(build, dtype=dtype, **window)[17]
        for role in ("source", "condition", "target"):
            assert s[role].dtype == dtype
            assert torch.equal(s[role], to_unit_range(raw[role], dtype))
        assert torch.equal(s["rel_pose"], raw["rel_pose"]) and s["pair_id"] == raw["pair_id"]


def test_resized_and_cropped_uint8_and_float_samples_agree(build):
    raw = PairDataset(build, dtype="uint8", output_size=(32, 32), num_frames=2)[3]
    s = PairDataset(build, dtype="float32", output_size=(32, 32), num_frames=2)[3]
    assert raw["target"].shape == (2, 3, 32, 32)
    assert torch.equal(s["target"], to_unit_range(raw["target"]))
    assert s["target"].min() >= -1 and s["target"].max() <= 1
    # the area filter scales each colour plane: near a full decode scaled by torch, then cut
    full = torch.from_numpy(decode_frames(media(build, PairDataset(build).row(3)["target_uri"]))[:2])
    scaled = torch.nn.functional.interpolate(full.permute(0, 3, 1, 2).float(), size=(32, 43), mode="area")
    assert (raw["target"].float() - scaled[..., 5:37]).abs().mean() < 3.0


@pytest.mark.parametrize("dtype", ["uint8", "float32", "bfloat16"])
def test_frame_buffers_are_reused_only_once_nothing_holds_the_sample(build, dtype):
    ds = PairDataset(build, dtype=dtype, num_frames=4)
    first = ds[5]
    kept = {role: first[role].clone() for role in ("source", "condition", "target")}
    addresses = {first[role].data_ptr() for role in kept}
    second = ds[40]   # the first sample is still held: its memory must not be written
    for role, frames in kept.items():
        assert torch.equal(first[role], frames)
    assert not addresses & {second[role].data_ptr() for role in kept}
    # a slice of the first sample outlives it: that buffer is still taken, the other two are free
    held = first["target"][1:3]
    del first, second
    third = ds[17]
    assert held.data_ptr() not in {third[role].data_ptr() for role in kept}
    assert {third[role].data_ptr() for role in ("source", "condition")} <= addresses
    assert torch.equal(held, kept["target"][1:3])
    # a reused buffer holds exactly the new sample, not a mix with the old one
    fresh = PairDataset(build, dtype=dtype, num_frames=4, reuse_buffers=False)[17]
    for role in kept:
        assert torch.equal(third[role], fresh[role])
    assert ds.buffers.held_bytes() == 6 * third["source"].numel() * third["source"].element_size()


def test_without_reuse_every_sample_is_new_memory_and_a_pickled_pool_starts_empty(build):
    import pickle

    ds = PairDataset(build, dtype="uint8", num_frames=2, reuse_buffers=False)
    a = ds[0]["source"].data_ptr()
    assert ds.buffers.held_bytes() == 0 and a != 0
    pooled = PairDataset(build, dtype="uint8", num_frames=2)
    pooled[0]
    assert pooled.buffers.held_bytes() > 0
    assert pickle.loads(pickle.dumps(pooled.buffers)).held_bytes() == 0


@pytest.fixture(scope="module")
def wide_build(tmp_path_factory):
    """One pair of 3 frames of 256x192: a colour plane (49,152 pixels) is more than torch's
    grain size, the element count past which one torch op is split over its intra-op threads."""
    data = tmp_path_factory.mktemp("wide")
    scene = write_clip_scene(data / "data", "synthetic-wide", clips=("front",), offsets=(2.0,),
                             conditions=(100,), num_frames=3, width=256, height=192)
    build_manifest(data / "b", [scenes_entry(scene)], stage_params("manifest", {}))
    return data / "b"


# torch splits an op over its intra-op threads only past this many elements (at::internal::GRAIN_SIZE)
TORCH_GRAIN_SIZE = 32768
# what torch.from_numpy and Tensor.numpy() record: none of them computes or copies
NON_COMPUTING_OPS = {"aten::view", "aten::to", "aten::detach", "detach", "aten::lift_fresh",
                     "aten::resolve_conj", "aten::resolve_neg", "aten::alias", "aten::as_strided"}


@pytest.mark.parametrize("dtype", ["uint8", "float32", "bfloat16", "float16"])
def test_reading_a_sample_runs_no_torch_op_that_threads_could_split(wide_build, dtype):
    """On a machine whose cores are busy, every torch op split over intra-op threads waits for
    threads that get no core: the frame path must run none, whatever the caller's thread count."""
    from torch.profiler import ProfilerActivity, profile

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        ds = PairDataset(wide_build, dtype=dtype)
        ds[0]
        with profile(activities=[ProfilerActivity.CPU], record_shapes=True) as prof:
            sample = ds[0]
        threads = torch.get_num_threads()
    finally:
        torch.set_num_threads(before)
    assert sample["target"].shape == (3, 3, 192, 256)
    splittable = {(e.name, n) for e in prof.events()
                  for n in [max((int(np.prod(s)) for s in e.input_shapes if s), default=0)]
                  if n > TORCH_GRAIN_SIZE and e.name not in NON_COMPUTING_OPS}
    assert not splittable
    assert threads == 2   # the caller's setting is left as it was


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16, torch.float16])
def test_every_byte_value_normalises_exactly_as_to_unit_range(dtype):
    from paradrive.data import frame_array, output_geometry, plane_sink

    values = np.arange(256, dtype=np.uint8).reshape(16, 16)
    out = torch.empty((1, 3, 16, 16), dtype=dtype, device="cpu")
    array = frame_array(out)
    plane_sink(lambda idx: array[idx], output_geometry(16, 16, None), dtype)(0, (values,) * 3)
    expected = to_unit_range(torch.from_numpy(values), dtype)
    assert all(torch.equal(out[0, c].view(torch.int16 if out.element_size() == 2 else torch.int32),
                           expected.view(torch.int16 if out.element_size() == 2 else torch.int32))
               for c in range(3))


def test_an_unknown_dtype_is_refused_with_the_choices(build):
    with pytest.raises(ValueError, match="uint8, float32, float16, bfloat16"):
        PairDataset(build, dtype="int16")
    with pytest.raises(TypeError, match="uint8"):
        to_unit_range(torch.zeros(2, dtype=torch.float32))


@pytest.mark.parametrize("start", [0, 40, 61, 96])
def test_a_window_decodes_from_the_keyframe_before_it_not_from_the_start(long_build, start):
    ds = PairDataset(long_build, dtype="uint8", num_frames=25, frame_offset=start)
    s = ds[0]
    row = ds.row(0)
    for role in ("source", "condition", "target"):
        full = decode_frames(media(long_build, row[f"{role}_uri"]), seek=False)
        assert torch.equal(s[role], torch.from_numpy(full[start:start + 25]).permute(0, 3, 1, 2))
    keyframe = start // 30 * 30  # the clip has a keyframe every 30 frames
    # per video: from the keyframe to the window's end, plus what the decoder holds back
    assert ds.frames_decoded <= 3 * (start + 25 - keyframe + 4)
    if start >= 30:
        assert ds.frames_decoded < 3 * (start + 25)  # a decode from frame 0 would need this many


def test_a_window_beyond_the_clip_is_refused_with_the_fix(build):
    ds = PairDataset(build, num_frames=5, frame_stride=2)
    with pytest.raises(ValueError, match="clip has 8"):
        ds[0]


def test_resize_and_centre_crop_adjust_the_intrinsics(build):
    ds = PairDataset(build, output_size=(32, 32))
    s = ds[0]
    assert s["target"].shape == (8, 3, 32, 32)
    # 64x48 -> scale 2/3 covers 32x32 at 43x32, centre crop starts at x = 5.
    geo = output_geometry(64, 48, (32, 32))
    assert geo["resize"] == (32, 43) and geo["crop"] == (0, 5)
    sx, sy = 43 / 64, 32 / 48
    np.testing.assert_allclose(s["intrinsics"].numpy(),
                               [50 * sx, 50 * sy, 32 * sx - 5, 24 * sy], rtol=1e-6)
    stretched = PairDataset(build, output_size=(24, 16), resize="stretch")[0]
    np.testing.assert_allclose(stretched["intrinsics"].numpy(), [12.5, 25, 8, 12], rtol=1e-6)


def test_recammaster_camera_is_target_relative_to_the_first_source_frame(long_build):
    ds = PairDataset(long_build, pose_format="recammaster", output_size=(16, 16))
    s = ds[0]
    assert s["camera"].shape == (31, 12) and s["target"].shape == (121, 3, 16, 16)
    cam = s["camera"].numpy().reshape(31, 3, 4)
    np.testing.assert_allclose(cam[:, :, :3], np.broadcast_to(np.eye(3), (31, 3, 3)), atol=1e-5)
    # Target of frame 4k seen from the source camera at frame 0: d to its right (camera +x) and
    # 4k metres ahead (the car drives 1 m per frame along camera z).
    np.testing.assert_allclose(cam[:, 0, 3], 2.0, atol=1e-4)
    np.testing.assert_allclose(cam[:, 2, 3], 4.0 * np.arange(31), atol=1e-4)
    np.testing.assert_allclose(cam[:, 1, 3], 0.0, atol=1e-4)


def test_recammaster_camera_function_matches_its_definition():
    rng = np.random.default_rng(0)
    tgt = np.stack([geometry.make_pose(geometry.rotation_about("y", a), rng.normal(size=3))
                    for a in rng.normal(size=9)])
    src = tgt @ geometry.translation(x=-1.0)
    cam = recammaster_camera(tgt, src)
    assert cam.shape == (3, 12)
    for k, f in enumerate((0, 4, 8)):
        expect = (np.linalg.inv(src[0]) @ tgt[f])[:3, :4].reshape(12)
        np.testing.assert_allclose(cam[k], expect, atol=1e-5)


def test_verify_checksums_names_a_corrupt_file(build, tmp_path):
    copy = tmp_path / "b"
    shutil.copytree(build, copy)
    ds = PairDataset(copy, verify_checksums=True)
    ds[0]  # clean files pass
    victim = media(copy, ds.row(1)["source_uri"])
    data = bytearray(victim.read_bytes())
    data[-5] ^= 0xFF
    victim.unlink()  # hardlinked: write a new file rather than change the original
    victim.write_bytes(bytes(data))
    with pytest.raises(ParaDriveError, match=re.escape(str(victim))):
        PairDataset(copy, verify_checksums=True)[1]


# --------------------------------------------------------------------------- ranks x workers

def loader_order(ds: PairIterableDataset, num_workers: int) -> list[int]:
    """The order a DataLoader delivers: batches taken from the workers in turn."""
    per_worker = [list(ds.worker_order(w, num_workers)) for w in range(num_workers)]
    b = ds.batch_size
    batches = [[ws[i:i + b] for i in range(0, len(ws), b)] for ws in per_worker]
    out = []
    for k in range(max(len(x) for x in batches)):
        for w in range(num_workers):
            if k < len(batches[w]):
                out.extend(batches[w][k])
    return out


@pytest.mark.parametrize("partition", ["pad", "drop"])
def test_ranks_and_workers_cover_the_build_without_overlap(build, partition):
    world, workers = 5, 3  # 144 pairs do not divide by 5
    seen = []
    counts = []
    for rank in range(world):
        ds = PairIterableDataset(build, rank=rank, world_size=world, batch_size=2, seed=3,
                                 partition=partition)
        ds.set_epoch(1)
        parts = [list(ds.worker_order(w, workers)) for w in range(workers)]
        flat = [i for p in parts for i in p]
        assert sorted(flat) == sorted(ds.rank_order())
        assert loader_order(ds, workers) == list(ds.rank_order())
        counts.append(len(flat))
        seen.extend(flat)
    assert len(set(counts)) == 1 and counts[0] == len(ds)
    if partition == "pad":
        assert counts[0] == 29 and set(seen) == set(range(144))
        assert len(seen) - len(set(seen)) == 1  # one pair repeated to even out the ranks
    else:
        assert counts[0] == 28 and len(set(seen)) == len(seen) == 140


def test_shuffle_is_deterministic_in_seed_and_epoch(build):
    a = PairIterableDataset(build, seed=1)
    b = PairIterableDataset(build, seed=1)
    a.set_epoch(4)
    b.set_epoch(4)
    assert list(a.epoch_order()) == list(b.epoch_order())
    assert list(a.epoch_order(5)) != list(a.epoch_order(4))
    assert list(PairIterableDataset(build, seed=2).epoch_order(4)) != list(a.epoch_order())
    assert list(PairIterableDataset(build, shuffle=False).epoch_order()) == list(range(144))


def test_state_dict_resumes_exactly_mid_epoch_with_workers(build):
    world, workers, batch = 2, 2, 3
    for rank in range(world):
        ds = PairIterableDataset(build, rank=rank, world_size=world, batch_size=batch, seed=9)
        ds.set_epoch(2)
        full = loader_order(ds, workers)
        state = ds.state_dict(samples_consumed=4 * batch)  # four batches trained on
        resumed = PairIterableDataset(build, rank=rank, world_size=world, batch_size=batch, seed=9)
        resumed.load_state_dict(state)
        assert resumed.epoch == 2
        rest = loader_order(resumed, workers)
        assert rest == full[4 * batch:]
        # A second save during the resumed epoch counts from the epoch start.
        assert resumed.state_dict(samples_consumed=3)["samples_consumed"] == 4 * batch + 3
        resumed.set_epoch(3)  # the next epoch starts from its beginning
        assert loader_order(resumed, workers) == list(resumed.rank_order(3))


def test_real_dataloader_with_workers_delivers_the_rank_sequence_and_resumes(build):
    ds = PairIterableDataset(build, rank=1, world_size=4, batch_size=2, seed=5, num_frames=2)
    ds.set_epoch(1)
    expected = [ds.dataset.pair_ids[i] for i in ds.rank_order()]
    loader = DataLoader(ds, batch_size=2, num_workers=2)
    got = [pid for batch in loader for pid in batch["pair_id"]]
    assert got == expected and len(got) == 36
    batch = next(iter(loader))
    assert batch["source"].shape == (2, 2, 3, 48, 64)

    state = ds.state_dict(samples_consumed=10)
    again = PairIterableDataset(build, rank=1, world_size=4, batch_size=2, seed=5, num_frames=2)
    again.load_state_dict(state)
    got = [pid for b in DataLoader(again, batch_size=2, num_workers=2) for pid in b["pair_id"]]
    assert got == expected[10:]


def test_without_workers_the_dataset_counts_what_it_yielded(build):
    ds = PairIterableDataset(build, rank=0, world_size=8, seed=0, num_frames=1)
    it = iter(ds)
    first = [next(it)["pair_id"] for _ in range(5)]
    state = ds.state_dict()
    assert state["samples_consumed"] == 5
    again = PairIterableDataset(build, rank=0, world_size=8, seed=0, num_frames=1)
    again.load_state_dict(state)
    rest = [s["pair_id"] for s in again]
    assert first + rest == [ds.dataset.pair_ids[i] for i in ds.rank_order()]


def test_resume_with_other_settings_is_refused(build):
    state = PairIterableDataset(build, world_size=2, rank=0).state_dict(samples_consumed=3)
    with pytest.raises(ValueError, match="world_size"):
        PairIterableDataset(build, world_size=4, rank=0).load_state_dict(state)


# --------------------------------------------------------------------------- end to end

@pytest.mark.slow
def test_smoke_build_feeds_the_adapter_and_verifies(smoke_build):
    from test_inspect import invoke

    build = smoke_build["build_dir"]
    ds = PairDataset(build, verify_checksums=True, pose_format="recammaster")
    assert len(ds) == 72 * len(smoke_build["scene_uris"])
    s = ds[len(ds) // 2]
    assert s["target"].shape == (9, 3, 96, 160) and s["camera"].shape == (3, 12)
    t = s["rel_pose"][:, :3, 3]
    assert torch.allclose(t.norm(dim=1), torch.tensor(abs(s["offset_m"])).expand(9), atol=1e-4)
    result = invoke(build, "--verify", "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["verify"]["ok"]


# --------------------------------------------------------------------------- many rows

def copy_rows(build, dest, copies: int, shard_rows: int, row_group_rows: int = 64, edit=None):
    """``build``'s rows copied ``copies`` times under new scene ids (in pair ids, scene ids and
    URIs), published at ``dest`` in shards of ``shard_rows``; ``edit(table)`` may change the rows
    first. The copies' videos do not exist: only opening the build is under test."""
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    from paradrive.contracts.records import IndexRecord
    from paradrive.pairs import SCHEMA

    base = read_pairs(build)
    renamed = ("pair_id", "scene_id", "source_uri", "condition_uri", "target_uri")
    table = pa.concat_tables([
        pa.table({name: pc.replace_substring(base.column(name), "synthetic-", f"copy{k:04d}-")
                  if name in renamed else base.column(name) for name in base.column_names}, schema=SCHEMA)
        for k in range(copies)])
    table = edit(table) if edit else table
    (dest / "v-000001").mkdir(parents=True)
    shards = []
    for i, start in enumerate(range(0, table.num_rows, shard_rows)):
        shard, name = table.slice(start, shard_rows), f"pairs-{i:05d}.parquet"
        pq.write_table(shard, dest / "v-000001" / name, row_group_size=row_group_rows)
        data = (dest / "v-000001" / name).read_bytes()   # the adapter checks a shard's sha256
        shards.append({"file": name, "rows": shard.num_rows, "bytes": len(data),
                       "sha256": hashlib.sha256(data).hexdigest(),
                       "first_pair_id": shard["pair_id"][0].as_py(), "last_pair_id": shard["pair_id"][-1].as_py()})
    doc = read_index(build).model_dump()
    doc.update(version="v-000001", shards=shards, totals={**doc["totals"], "rows": table.num_rows,
                                                          "shards": len(shards)})
    IndexRecord.model_validate(doc).save(dest / "index.json")
    return dest, table


def test_rows_read_with_their_row_group_are_the_manifest_rows_across_shards(build, tmp_path):
    from paradrive.data import _ROW_COLUMNS

    copies = -(-400 // len(PairDataset(build)))
    large, table = copy_rows(build, tmp_path / "b", copies=copies, shard_rows=100, row_group_rows=7)
    ds = PairDataset(large)
    assert len(ds) == table.num_rows > 300 and ds.pair_ids == table["pair_id"].to_pylist()
    for i in (0, 6, 7, 99, 100, 101, 300, table.num_rows - 1):
        row, want = ds.row(i), table.slice(i, 1).to_pylist()[0]
        assert {name: row[name] for name in _ROW_COLUMNS} == {name: want[name] for name in _ROW_COLUMNS}
        for name in ("rel_pose", "target_c2w"):
            np.testing.assert_array_equal(row[name], np.asarray(want[name]).reshape(-1, 4, 4))


def test_opening_20k_rows_keeps_no_python_object_per_row(build, tmp_path):
    """The adapter keeps pair ids as Arrow and reads a row's columns with its row group: opening
    a build (and the dataset a DataLoader pickles for each worker) costs far less than the
    ~1 KB a row that Python lists of every column took."""
    import pickle
    import tracemalloc

    large, table = copy_rows(build, tmp_path / "b", copies=-(-20_000 // len(PairDataset(build))),
                             shard_rows=4096)
    rows = table.num_rows
    tracemalloc.start()
    try:
        ds = PairDataset(large)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(ds) == rows >= 20_000
    assert peak < 100 * rows, f"{peak} bytes of Python objects for {rows} rows"
    ds.row(rows - 1)   # opens a shard and caches a row group: neither goes to a worker
    worker = pickle.loads(pickle.dumps(ds))
    assert len(pickle.dumps(ds)) < 100 * rows
    assert worker.row(rows - 1)["pair_id"] == table["pair_id"][-1].as_py()


def test_a_bad_uri_names_the_first_row_that_holds_it(build, tmp_path):
    import pyarrow as pa

    from paradrive.io import PathEscapeError

    def escape(table):
        uris = table["condition_uri"].to_pylist()
        uris[150] = uris[210] = "../../outside.mp4"
        return table.set_column(table.schema.get_field_index("condition_uri"), "condition_uri",
                                pa.array(uris, pa.string()))

    copies = -(-250 // len(PairDataset(build)))
    large, table = copy_rows(build, tmp_path / "b", copies=copies, shard_rows=100, edit=escape)
    shard = version_dir(large, read_index(large)) / "pairs-00001.parquet"
    pair_id = table["pair_id"][150].as_py()
    with pytest.raises(PathEscapeError, match=rf"{re.escape(str(shard))}: row {re.escape(pair_id)} "
                                              rf"column condition_uri: path '\.\./\.\./outside\.mp4'"):
        PairDataset(large)


# --------------------------------------------------------------------------- arguments

@pytest.mark.parametrize("arguments, named", [
    ({"output_size": (0, 0)}, "PairDataset(output_size=(0, 0)): must be (height, width), two integers >= 1"),
    ({"output_size": (-8, 16)}, "PairDataset(output_size=(-8, 16)): must be (height, width)"),
    ({"output_size": (32, 32, 3)}, "PairDataset(output_size=(32, 32, 3)): must be (height, width)"),
    ({"output_size": 32}, "PairDataset(output_size=32): must be (height, width)"),
    ({"output_size": (32.5, 32)}, "PairDataset(output_size=(32.5, 32)): must be (height, width)"),
    ({"num_frames": 0}, "PairDataset(num_frames=0): must be an integer >= 1, or None"),
    ({"num_frames": True}, "PairDataset(num_frames=True): must be an integer >= 1"),
    ({"frame_stride": 0}, "PairDataset(frame_stride=0): must be an integer >= 1"),
    ({"frame_offset": -1}, "PairDataset(frame_offset=-1): must be an integer >= 0"),
    ({"resize": "fit"}, "PairDataset(resize='fit'): must be 'crop' or 'stretch'"),
    ({"pose_format": "plucker"}, "PairDataset(pose_format='plucker'): must be None or 'recammaster'"),
    ({"prompt": None}, "PairDataset(prompt=None): must be a string"),
    ({"decode_threads": -1}, "PairDataset(decode_threads=-1): must be an integer >= 0"),
    ({"dtype": "int16"}, "PairDataset(dtype='int16'): must be one of uint8, float32, float16, bfloat16"),
    ({"verify_checksums": "yes"}, "PairDataset(verify_checksums='yes'): must be True or False"),
    ({"reuse_buffers": 1}, "PairDataset(reuse_buffers=1): must be True or False"),
    ({"latents": "auto"}, "PairDataset(latents='auto'): must be True or False"),
    ({"latents": True, "num_frames": 5}, "PairDataset(latents=True, num_frames=5): the latent cache fixed"),
    ({"latents": True, "output_size": (24, 40)}, "PairDataset(latents=True, output_size=(24, 40)): the latent"),
    ({"latents": True, "dtype": "uint8"}, "PairDataset(latents=True, dtype='uint8'): latents are floating"),
    ({"seed": -1}, "PairIterableDataset(seed=-1): must be an integer >= 0"),
    ({"batch_size": 0}, "PairIterableDataset(batch_size=0): must be an integer >= 1"),
    ({"world_size": 0}, "PairIterableDataset(world_size=0): must be an integer >= 1"),
    ({"rank": 2, "world_size": 2}, "PairIterableDataset(rank=2): must be below world_size (2)"),
    ({"partition": "even"}, "PairIterableDataset(partition='even'): must be 'pad' or 'drop'"),
    ({"shuffle": None}, "PairIterableDataset(shuffle=None): must be True or False"),
])
def test_a_wrong_argument_is_refused_in_one_line_naming_it_before_the_build_is_opened(tmp_path, arguments, named):
    # tmp_path holds no build: the arguments are refused before anything is read
    cls = PairIterableDataset if named.startswith("PairIterableDataset") else PairDataset
    with pytest.raises(ValueError) as refused:
        cls(tmp_path / "no-build", **arguments)
    message = str(refused.value)
    assert message.startswith(named) and "\n" not in message


def test_numpy_integers_and_a_list_size_are_accepted(build):
    sample = PairDataset(build, dtype="uint8", num_frames=np.int64(2), output_size=[np.int32(16), 32])[0]
    assert sample["target"].shape == (2, 3, 16, 32)


def test_with_latents_a_prompt_is_refused_since_the_cache_holds_the_empty_prompt_alone(tmp_path):
    with pytest.raises(ValueError) as refused:
        PairDataset(tmp_path / "no-build", latents=True, prompt="a street at night")
    assert str(refused.value).startswith("PairDataset(latents=True, prompt='a street at night'): the "
                                         "latent cache holds the text embedding of the empty prompt alone")
