"""The manifest stage: pair rows, poses, checksums, shards, index and atomic publishing.

``write_clip_scene`` makes a scene folder the way the clip stage leaves it (real H.264 / FFV1
files written with PyAV and a clips.json), so these tests do not need the whole pipeline; the
end-to-end test at the bottom runs on the ``smoke_build`` fixture when every stage is present.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from conftest import stage_params

from paradrive import geometry
from paradrive.errors import ParaDriveError
from paradrive.pairs import SCHEMA, make_pair_id, read_index, read_pairs, version_dir
from paradrive.stages.manifest import build_manifest
from paradrive.manifest import scene_rows

ROOT = Path(__file__).resolve().parents[1]
OFFSETS = (1.0, -1.0, 2.0, -2.0, 3.0, -3.0, 4.0, -4.0)
CONDITIONS = (100, 500, 1000)
CAM2EGO_FRONT = geometry.make_pose(geometry.OPENCV_TO_FLU, [1.5, 0.0, 1.6])


# --------------------------------------------------------------------------- fixtures

def frame_pixels(stream_seed: int, index: int, width: int, height: int) -> np.ndarray:
    """A frame whose content names its stream and index: a flat level that rises with the
    index plus a gradient, so order and values can be checked after decoding."""
    y, x = np.mgrid[0:height, 0:width]
    img = np.empty((height, width, 3), np.uint8)
    img[..., 0] = (20 + 9 * index + stream_seed * 7) % 256
    img[..., 1] = (x * 255 // max(1, width - 1)).astype(np.uint8)
    img[..., 2] = (y * 255 // max(1, height - 1)).astype(np.uint8)
    return img


def write_video(path: Path, frames: list[np.ndarray], fps: float = 10.0, codec: str = "libx264",
                gop: int = 4) -> None:
    import av

    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    with av.open(str(path), "w") as out:
        stream = out.add_stream(codec, rate=int(round(fps)))
        stream.width, stream.height = w, h
        if codec == "libx264":
            stream.pix_fmt = "yuv420p"
            stream.options = {"crf": "12", "preset": "ultrafast", "g": str(gop),
                              "keyint_min": str(gop)}
        else:
            stream.pix_fmt = "bgr0"
        for img in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(img, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)


def scene_poses(n_total: int, speed: float = 1.0):
    """ego2world and front-camera c2w (n_total, 4, 4) for a car driving along world x."""
    ego = np.stack([geometry.translation(x=speed * i) for i in range(n_total)])
    return ego, ego @ CAM2EGO_FRONT


def write_clip_scene(data_dir: Path, scene_id: str, *, dataset: str = "synthetic",
                     clips=("front", "middle", "rear"), offsets=OFFSETS, conditions=CONDITIONS,
                     num_frames: int = 8, width: int = 64, height: int = 48,
                     codec: str = "libx264", gop: int = 4, quality: bool = True) -> Path:
    """A scene folder with ``clips/clips.json`` and every stream encoded, as the clip stage
    writes it. Returns the scene folder."""
    scene_dir = data_dir / "scenes" / scene_id
    fps = 10.0
    total = num_frames * 3
    ego, c2w = scene_poses(total)
    ext = "mp4" if codec == "libx264" else "mkv"
    doc = {"schema_version": 1, "scene_id": scene_id, "dataset": dataset,
           "source": f"synthetic:{scene_id}", "fps": fps, "width": width, "height": height,
           "codec": codec,
           "cameras": {"front": {"intrinsics": [50.0, 50.0, width / 2, height / 2]}},
           "fit": {"iteration": 30000, "train_psnr": 31.2, "train_ssim": 0.93},
           "clips": [], "skipped": [{"camera": "front", "clip": "extra", "reason": "too short"}]}
    starts = {"front": 0, "middle": num_frames, "rear": 2 * num_frames}
    for clip in clips:
        start = starts[clip]
        idx = list(range(start, start + num_frames))
        streams, quality_doc = {}, {}

        def add(name, seed, extra):
            rel = f"clips/front/{clip}/{name}.{ext}"
            frames = [frame_pixels(seed, i, width, height) for i in range(num_frames)]
            write_video(scene_dir / rel, frames, fps, codec, gop)
            data = (scene_dir / rel).read_bytes()
            streams[name] = {"file": rel, "bytes": len(data),
                             "sha256": hashlib.sha256(data).hexdigest(), **extra}

        add("target", 0, {"kind": "target"})
        for it in conditions:
            add(f"cond@{it:06d}", it % 13 + 1, {"kind": "condition", "iteration": it})
            if quality:
                quality_doc[f"cond@{it:06d}"] = {"psnr": 15.0 + it / 100, "ssim": 0.5}
        for d in offsets:
            shifted = geometry.lateral_shift(c2w[idx], ego[idx], d)
            add(f"source{d:+g}m", int(d * 3) % 11 + 2,
                {"kind": "source", "iteration": 30000, "offset_m": d,
                 "c2w": [m.reshape(16).tolist() for m in shifted]})
        doc["clips"].append({"camera": "front", "clip": clip, "frame_start": start,
                             "num_frames": num_frames, "frame_indices": idx,
                             "timestamps_us": [i * 100_000 for i in idx],
                             "c2w": [m.reshape(16).tolist() for m in c2w[idx]],
                             "streams": streams, "quality": quality_doc})
    (scene_dir / "clips" / "clips.json").write_text(json.dumps(doc))
    return scene_dir


def scenes_entry(scene_dir: Path) -> dict:
    return {"scene_id": scene_dir.name, "scene_uri": f"synthetic:{scene_dir.name}",
            "scene_dir": str(scene_dir)}


@pytest.fixture(scope="module")
def two_scene_data(tmp_path_factory):
    data = tmp_path_factory.mktemp("clipdata")
    return [write_clip_scene(data, "synthetic-a"), write_clip_scene(data, "synthetic-b")]


@pytest.fixture(scope="module")
def built(tmp_path_factory, two_scene_data):
    build_dir = tmp_path_factory.mktemp("manifests") / "b1"
    params = {"shard_rows": 50, "row_group_rows": 16, "media": "hardlink"}
    build_manifest(build_dir, [scenes_entry(s) for s in two_scene_data],
                   stage_params("manifest", params), fingerprint="fp-1")
    return build_dir


# --------------------------------------------------------------------------- rows

def test_every_scene_gives_72_pairs_3_clips_8_offsets_3_checkpoints(built):
    table = read_pairs(built)
    df = table.select(["scene_id", "clip", "offset_m", "condition_iteration"]).to_pandas()
    assert len(df) == 144
    assert df.groupby("scene_id").size().to_dict() == {"synthetic-a": 72, "synthetic-b": 72}
    per = df.groupby(["scene_id", "clip", "offset_m", "condition_iteration"]).size()
    assert len(per) == 144 and per.max() == 1
    assert sorted(df.offset_m.unique()) == sorted(OFFSETS)
    assert sorted(df.condition_iteration.unique()) == list(CONDITIONS)


def test_rows_are_sorted_by_stable_pair_id(built):
    ids = read_pairs(built, ["pair_id"]).column("pair_id").to_pylist()
    assert ids == sorted(ids)
    assert "synthetic/synthetic-a/front/middle/+2m/000500" in ids
    assert "synthetic/synthetic-b/front/rear/-4m/001000" in ids
    assert make_pair_id("waymo", "s", "front", "middle", 2.0, 500) == "waymo/s/front/middle/+2m/000500"


def test_table_has_the_documented_schema(built):
    table = read_pairs(built)
    assert table.schema.equals(SCHEMA, check_metadata=False)
    schema_doc = (ROOT / "manifests" / "SCHEMA.md").read_text()
    for name in SCHEMA.names:
        assert f"`{name}`" in schema_doc, f"column {name} is not documented in SCHEMA.md"


def test_rel_pose_is_a_lateral_translation_toward_the_source_side(built):
    table = read_pairs(built, ["offset_m", "rel_pose", "target_c2w", "num_frames"])
    for row in table.to_pylist():
        d = row["offset_m"]
        rel = np.asarray(row["rel_pose"], np.float64).reshape(-1, 4, 4)
        assert rel.shape == (row["num_frames"], 4, 4)
        t = rel[:, :3, 3]
        np.testing.assert_allclose(np.linalg.norm(t, axis=1), abs(d), atol=1e-5)
        np.testing.assert_allclose(rel[:, :3, :3], np.broadcast_to(np.eye(3), (len(rel), 3, 3)),
                                   atol=1e-6)
        # The source sits d metres to the ego's left (+y ego). A forward camera's x axis points
        # right (= -y ego), so in target camera coordinates the source is at x = -d.
        np.testing.assert_allclose(t[:, 0], -d, atol=1e-5)
        np.testing.assert_allclose(t[:, 1:], 0.0, atol=1e-5)
        # And the same thing in the world: c2w_source = c2w_target @ rel_pose is d to the left.
        c2w_t = np.asarray(row["target_c2w"]).reshape(-1, 4, 4)
        left_world = c2w_t[:, :3, :3] @ np.array([-1.0, 0.0, 0.0])  # camera -x = ego left
        np.testing.assert_allclose((c2w_t @ rel)[:, :3, 3] - c2w_t[:, :3, 3],
                                   d * left_world, atol=1e-5)


def test_checksums_and_sizes_match_the_linked_media(built):
    table = read_pairs(built).to_pylist()
    seen = {}
    for row in table:
        for role in ("source", "condition", "target"):
            seen[row[f"{role}_uri"]] = (row[f"{role}_sha256"], row[f"{role}_bytes"])
    assert len(seen) == 2 * 3 * (1 + 3 + 8)
    folder = version_dir(built, read_index(built))
    for uri, (sha, size) in seen.items():
        path = folder / uri
        assert uri.startswith("media/") and path.is_file()
        data = path.read_bytes()
        assert len(data) == size and hashlib.sha256(data).hexdigest() == sha


def test_quality_and_fit_figures_come_from_clips_json(built):
    df = read_pairs(built, ["condition_iteration", "condition_psnr", "fit_train_psnr"]).to_pandas()
    for it, group in df.groupby("condition_iteration"):
        assert np.allclose(group.condition_psnr, 15.0 + it / 100)
    assert np.allclose(df.fit_train_psnr, 31.2)


def test_missing_quality_is_computed_from_the_videos(tmp_path):
    scene = write_clip_scene(tmp_path, "synthetic-q", clips=("middle",), offsets=(1.0,),
                             conditions=(100,), quality=False)
    rows, _, _ = scene_rows(scene)
    assert 5.0 < rows[0]["condition_psnr"] < 60.0 and 0.0 < rows[0]["condition_ssim"] <= 1.0
    rows, _, _ = scene_rows(scene, quality=False)
    assert rows[0]["condition_psnr"] is None


# --------------------------------------------------------------------------- index, shards

def test_index_lists_shards_with_rows_bytes_and_sha256(built):
    index = read_index(built)
    assert index.config_fingerprint == "fp-1"
    assert index.software["paradrive"]
    assert [s.rows for s in index.shards] == [50, 50, 44]
    assert index.totals.rows == 144
    assert index.version == "v-000001"
    for s in index.shards:
        assert re.fullmatch(r"pairs-\d{5}\.parquet", s.file)
        data = (built / index.version / s.file).read_bytes()
        assert len(data) == s.bytes and hashlib.sha256(data).hexdigest() == s.sha256
        assert pq.ParquetFile(built / index.version / s.file).metadata.num_rows == s.rows
    assert [c.name for c in index.columns] == SCHEMA.names
    assert {s.scene_id for s in index.scenes} == {"synthetic-a", "synthetic-b"}
    assert index.scenes[0].skipped_clips[0].clip == "extra"


def test_shards_can_be_capped_by_bytes(tmp_path, two_scene_data):
    build = tmp_path / "bybytes"
    index = build_manifest(build, [scenes_entry(two_scene_data[0])],
                           stage_params("manifest", {"shard_rows": 1000, "shard_bytes": 20_000}))
    rows = [s.rows for s in index.shards]
    assert sum(rows) == 72 and len(rows) > 1


def test_adding_scenes_keeps_the_old_rows(tmp_path, two_scene_data, built):
    single = tmp_path / "single"
    build_manifest(single, [scenes_entry(two_scene_data[0])], stage_params("manifest", {"shard_rows": 7}))
    old = read_pairs(single).to_pandas().set_index("pair_id")
    both = read_pairs(built).to_pandas().set_index("pair_id")
    assert len(old) == 72
    common = both.loc[old.index]
    for col in old.columns:
        assert [repr(v) for v in old[col]] == [repr(v) for v in common[col]], col


def test_republishing_keeps_foreign_files_and_drops_stale_shards(tmp_path, two_scene_data):
    build = tmp_path / "b"
    entries = [scenes_entry(s) for s in two_scene_data]
    build_manifest(build, entries, stage_params("manifest", {"shard_rows": 10}))
    first = version_dir(build, read_index(build))
    assert first.name == "v-000001" and len(list(first.glob("pairs-*.parquet"))) == 15
    (build / "ledger.sqlite").write_bytes(b"ledger")
    (build / "logs").mkdir()
    (build / "logs" / "run.log").write_text("log")
    build_manifest(build, entries[:1], stage_params("manifest", {"shard_rows": 100}))
    second = version_dir(build, read_index(build))
    assert second.name == "v-000002" and first.is_dir()   # the old one stays for its readers
    assert sorted(p.name for p in second.glob("pairs-*.parquet")) == ["pairs-00000.parquet"]
    assert (build / "ledger.sqlite").read_bytes() == b"ledger"
    assert (build / "logs" / "run.log").read_text() == "log"
    assert not (second / "media" / "synthetic-b").exists()
    assert not [p for p in build.rglob("*") if ".tmp-" in p.name or "staging" in p.name]
    assert read_index(build).totals.rows == 72


def test_media_hardlinks_share_the_inode_and_copy_does_not(tmp_path, two_scene_data):
    src = two_scene_data[0] / "clips/front/middle/target.mp4"
    rel = "media/synthetic-a/clips/front/middle/target.mp4"
    for mode, same in (("hardlink", True), ("copy", False)):
        build = tmp_path / mode
        build_manifest(build, [scenes_entry(two_scene_data[0])], stage_params("manifest", {"media": mode}))
        dst = version_dir(build, read_index(build)) / rel
        assert (os.stat(dst).st_ino == os.stat(src).st_ino) is same
        assert dst.read_bytes() == src.read_bytes()
    build = tmp_path / "symlink"
    build_manifest(build, [scenes_entry(two_scene_data[0])], stage_params("manifest", {"media": "symlink"}))
    assert (version_dir(build, read_index(build)) / rel).is_symlink()


def test_a_bad_scene_is_skipped_with_its_reason(tmp_path, two_scene_data):
    import shutil

    bad = tmp_path / "data" / "scenes" / "synthetic-bad"
    shutil.copytree(two_scene_data[1], bad)
    doc = json.loads((bad / "clips/clips.json").read_text())
    doc["scene_id"] = "synthetic-bad"
    (bad / "clips/clips.json").write_text(json.dumps(doc))
    victim = bad / "clips/front/rear/cond@000500.mp4"
    victim.write_bytes(victim.read_bytes()[:-10] + b"0123456789")
    index = build_manifest(tmp_path / "b", [scenes_entry(two_scene_data[0]), scenes_entry(bad)],
                           stage_params("manifest", {}))
    assert index.totals.rows == 72
    (skip,) = index.skipped_scenes
    assert skip.scene_id == "synthetic-bad"
    assert "cond@000500" in skip.reason and "sha256" in skip.reason


def test_no_usable_scene_is_an_error_naming_clips_json(tmp_path):
    (tmp_path / "scenes" / "x").mkdir(parents=True)
    with pytest.raises(ParaDriveError, match="clips.json is missing"):
        build_manifest(tmp_path / "b", [{"scene_id": "x", "scene_dir": str(tmp_path / "scenes/x")}],
                       stage_params("manifest", {}))
    assert not (tmp_path / "b" / "index.json").exists()


def test_reading_a_folder_without_index_says_what_to_do(tmp_path):
    with pytest.raises(ParaDriveError, match="index.json is missing"):
        read_index(tmp_path)


# --------------------------------------------------------------------------- SCHEMA.md examples

def _schema_examples(lang: str) -> list[str]:
    text = (ROOT / "manifests" / "SCHEMA.md").read_text()
    return re.findall(rf"```{lang}\n(.*?)```", text, re.S)


def test_schema_md_duckdb_example_runs_on_a_build(built, monkeypatch):
    duckdb = pytest.importorskip("duckdb")
    monkeypatch.chdir(built.parent)
    (sql,) = _schema_examples("sql")
    # the example names the version index.json names (older ones a publish keeps sit beside it)
    assert "manifests/default/v-000003/" in sql
    sql = sql.replace("manifests/default/v-000003/", f"{built.name}/{read_index(built).version}/")
    rows = duckdb.sql(sql).fetchall()
    assert rows and sum(r[-1] for r in rows) == 144


def test_schema_md_pandas_example_runs_on_a_build(built, monkeypatch):
    pytest.importorskip("pandas")
    monkeypatch.chdir(built.parent)
    (code,) = _schema_examples("python")
    code = code.replace("manifests/default", built.name)
    scope: dict = {}
    exec(compile(code, "SCHEMA.md", "exec"), scope)
    assert len(scope["df"]) == 144


# --------------------------------------------------------------------------- end to end

@pytest.mark.slow
def test_smoke_build_publishes_72_pairs_per_scene(smoke_build):
    build = smoke_build["build_dir"]
    index = read_index(build)
    assert index.totals.rows == 72 * len(smoke_build["scene_uris"])
    df = read_pairs(build, ["scene_id", "offset_m", "rel_pose"]).to_pandas()
    assert set(df.groupby("scene_id").size()) == {72}
    for d, poses in zip(df.offset_m, df.rel_pose):
        t = np.stack(poses).reshape(-1, 4, 4)[:, :3, 3]
        np.testing.assert_allclose(np.linalg.norm(t, axis=1), abs(d), atol=1e-4)
        assert np.all(np.sign(t[:, 0]) == -np.sign(d))  # front camera: source on its left
