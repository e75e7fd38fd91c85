"""The nuScenes table index: a scene reads the same with and without it, only its own rows come
out of it, it is built once by concurrent workers and rebuilt when a table changes."""

from __future__ import annotations

import json
import multiprocessing
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import stage_params

from paradrive.errors import SceneError
from paradrive.ingest import export, nuscenes
from paradrive.ingest.nuscenes_tables import (
    INDEX_DIR, INDEX_NAME, IndexedTables, JsonTables, open_tables, stream_rows,
)
from paradrive.scene import load_scene, write_scene
from paradrive.stages.ingest import ingest
from paradrive.synthetic import SyntheticStreet
from paradrive.uri import parse_uri
from synthetic_logs import street_log

VERSION = "v1.0-mini"
SCENES = ("scene-0061", "scene-0103")
PARAMS = stage_params("ingest", {"cameras": ["front", "front_left"], "image_ext": "png"})


def _merge(parts: list[Path], root: Path) -> Path:
    """One dataroot holding the scenes of ``parts`` (each written by export_nuscenes): rows
    appended table by table, rows two exports share (sensors, categories) kept once, and each
    part's instance tokens made its own (the street's actors have the same names)."""
    tables: dict[str, list[dict]] = {}
    for n, part in enumerate(parts):
        for path in sorted((part / VERSION).glob("*.json")):
            rows = json.loads(path.read_text())
            for row in rows:
                if path.stem == "instance":
                    row["token"] = f"{n}-{row['token']}"
                if path.stem == "sample_annotation":
                    row["instance_token"] = f"{n}-{row['instance_token']}"
            have = {r["token"] for r in tables.setdefault(path.stem, [])}
            tables[path.stem] += [r for r in rows if r["token"] not in have]
        for folder in ("samples", "sweeps"):
            shutil.copytree(part / folder, root / folder, dirs_exist_ok=True)
    (root / VERSION).mkdir(parents=True)
    for name, rows in tables.items():
        (root / VERSION / f"{name}.json").write_text(json.dumps(rows, indent=0))
    return root


@pytest.fixture(scope="module")
def dataroot(tmp_path_factory):
    """Two scenes in one dataroot: three cameras with LiDAR, and a curved street with traffic."""
    tmp = tmp_path_factory.mktemp("nus")
    first = street_log(5, 7, 64, 48, ("front", "front_left", "front_right"), lidar_seed=100,
                       lidar_points=500, lidar_extent_m=30)
    second = SyntheticStreet(seed=7, frames=16, width=64, height=48,
                             cameras=["front", "front_left"], curvature=0.004)
    export.export_nuscenes(first, tmp / "a", image_format="png", keyframe_every=3, scene_name=SCENES[0])
    export.export_nuscenes(second, tmp / "b", image_format="png", keyframe_every=5, lidar=False,
                           scene_name=SCENES[1])
    return _merge([tmp / "a", tmp / "b"], tmp / "root")


def _copy(dataroot: Path, tmp_path: Path) -> Path:
    root = tmp_path / "root"
    shutil.copytree(dataroot, root, ignore=shutil.ignore_patterns(INDEX_DIR))
    return root


def _uri(root: Path, scene: str) -> str:
    return f"nuscenes:{root}?version={VERSION}#{scene}"


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _read(root: Path, scene: str, out: Path, tables=None) -> dict[str, bytes]:
    uri = parse_uri(_uri(root, scene))
    write_scene(nuscenes.read(uri, out, PARAMS, uri.scene_id, tables), out)
    return _files(out)


@pytest.mark.parametrize("scene", SCENES)
def test_a_scene_reads_the_same_with_and_without_the_index(dataroot, tmp_path, scene):
    root = _copy(dataroot, tmp_path)
    whole = JsonTables.load(root / VERSION, "whole")
    without = _read(root, scene, tmp_path / "without", whole)
    assert not (root / VERSION / INDEX_DIR).exists()
    with_index = _read(root, scene, tmp_path / "with")
    assert (root / VERSION / INDEX_DIR / INDEX_NAME).is_file()
    assert with_index.keys() == without.keys()
    assert with_index == without  # scene.json (poses, actors) and every image and sweep, byte for byte
    doc = json.loads(with_index["scene.json"])
    assert doc["nuscenes"]["scene"] == scene
    if scene == SCENES[1]:
        assert doc["actors"]  # the traffic of the second street is in it


def test_a_scene_gets_only_its_own_rows_from_the_index(dataroot, tmp_path):
    root = _copy(dataroot, tmp_path)
    index = open_tables(root / VERSION, "s")
    assert isinstance(index, IndexedTables)
    whole = JsonTables.load(root / VERSION, "whole")
    for scene in whole.rows("scene"):
        samples = {s["token"] for s in whole.rows("sample") if s["scene_token"] == scene["token"]}
        rows = index.annotations_of(samples)
        assert rows == whole.annotations_of(samples)
        assert {r["sample_token"] for r in rows} <= samples
        first = index.sample_data_of(scene["first_sample_token"])
        assert first and all(sd["sample_token"] == scene["first_sample_token"] for sd in first)
    assert len(whole.rows("sample_annotation")) > len(rows) > 0  # the other scene's boxes stayed out


def test_ingest_builds_the_index_once_and_reuses_it(dataroot, tmp_path):
    root = _copy(dataroot, tmp_path)
    ingest(_uri(root, SCENES[0]), tmp_path / "a", PARAMS)
    index = root / VERSION / INDEX_DIR / INDEX_NAME
    built = index.stat().st_mtime_ns
    first = open_tables(root / VERSION, "s")
    ingest(_uri(root, SCENES[1]), tmp_path / "b", PARAMS)
    again = open_tables(root / VERSION, "s")
    assert index.stat().st_mtime_ns == built
    assert not again.built_here and again.meta["build_id"] == first.meta["build_id"]


def test_a_changed_table_rebuilds_the_index(dataroot, tmp_path):
    root = _copy(dataroot, tmp_path)
    ingest(_uri(root, SCENES[0]), tmp_path / "before", PARAMS)
    before = open_tables(root / VERSION, "s").meta["build_id"]
    leftover = root / VERSION / INDEX_DIR / f".{INDEX_NAME}.tmp-0badf00d"  # a builder killed mid-way
    leftover.write_bytes(b"half")
    path = root / VERSION / "ego_pose.json"
    rows = json.loads(path.read_text())
    frame_3 = json.loads(_files(tmp_path / "before")["scene.json"])["frames"][3]
    sd = next(r for r in json.loads((root / VERSION / "sample_data.json").read_text())
              if r["timestamp"] == frame_3["timestamp_us"] and "/CAM_FRONT/" in r["filename"])
    moved = next(r for r in rows if r["token"] == sd["ego_pose_token"])
    moved["translation"][2] += 0.5
    path.write_text(json.dumps(rows, indent=0))

    ingest(_uri(root, SCENES[0]), tmp_path / "after", PARAMS)
    after = open_tables(root / VERSION, "s")
    assert after.meta["build_id"] != before
    assert not leftover.exists()
    old, new = load_scene(tmp_path / "before"), load_scene(tmp_path / "after")
    shift = new.frames[3].ego2world[:3, 3] - old.frames[3].ego2world[:3, 3]
    assert np.isclose(np.linalg.norm(shift), 0.5)
    assert np.allclose(new.frames[2].ego2world, old.frames[2].ego2world)


def _open_in_worker(folder: str, barrier, results) -> None:
    barrier.wait()
    tables = open_tables(Path(folder), "worker")
    results.put((tables.meta["build_id"], tables.built_here))


def test_two_workers_build_the_index_once(dataroot, tmp_path):
    root = _copy(dataroot, tmp_path)
    ctx = multiprocessing.get_context("spawn")
    barrier, results = ctx.Barrier(2), ctx.Queue()
    workers = [ctx.Process(target=_open_in_worker, args=(str(root / VERSION), barrier, results))
               for _ in range(2)]
    for w in workers:
        w.start()
    found = [results.get(timeout=120) for _ in workers]
    for w in workers:
        w.join(timeout=60)
        assert w.exitcode == 0
    (build_a, built_a), (build_b, built_b) = found
    assert build_a == build_b  # both read the one index
    assert sorted([built_a, built_b]) == [False, True]  # and only one of them built it
    assert sorted(p.name for p in (root / VERSION / INDEX_DIR).iterdir()) == ["tables.lock", INDEX_NAME]


def test_an_index_folder_that_cannot_be_made_goes_to_the_cache(dataroot, tmp_path, monkeypatch):
    root = _copy(dataroot, tmp_path)
    (root / VERSION / INDEX_DIR).write_text("not a folder")  # as a read-only dataroot would refuse
    monkeypatch.setenv("PARADRIVE_CACHE", str(tmp_path / "cache"))
    tables = open_tables(root / VERSION, "s")
    assert isinstance(tables, IndexedTables)
    assert tables.path.is_relative_to(tmp_path / "cache" / "nuscenes")
    ingest(_uri(root, SCENES[0]), tmp_path / "scene", PARAMS)
    assert load_scene(tmp_path / "scene").frames


@pytest.mark.parametrize("chunk", [1, 7, 64, 1 << 20])
def test_streamed_rows_are_the_rows_json_loads_gives(dataroot, chunk):
    path = dataroot / VERSION / "sample_annotation.json"
    streamed = list(stream_rows(path, chunk_chars=chunk))
    assert [row for row, _ in streamed] == json.loads(path.read_text())
    assert all(json.loads(text) == row for row, text in streamed)


@pytest.mark.parametrize("damage", ["truncate", "not a list", "trailing text"])
def test_a_malformed_table_is_named(dataroot, tmp_path, damage):
    root = _copy(dataroot, tmp_path)
    path = root / VERSION / "sample_data.json"
    text = path.read_text()
    path.write_text({"truncate": text[: len(text) // 2], "not a list": '{"token": "x"}',
                     "trailing text": text + "{}"}[damage])
    with pytest.raises(SceneError, match=r"table sample_data.json is malformed \(.*\) \(.*sample_data.json\); "
                                         r"re-extract"):
        ingest(_uri(root, SCENES[0]), tmp_path / "s", PARAMS)
    assert not list((root / VERSION / INDEX_DIR).glob(f".{INDEX_NAME}*"))  # nothing half-written


def test_a_token_on_two_rows_is_named_by_both_readers(dataroot, tmp_path):
    root = _copy(dataroot, tmp_path)
    path = root / VERSION / "ego_pose.json"
    rows = json.loads(path.read_text())
    path.write_text(json.dumps(rows + [rows[3]], indent=0))
    twice = rf"table ego_pose.json is malformed \(token '{rows[3]['token']}' is on two rows\)"
    with pytest.raises(SceneError, match=twice):
        open_tables(root / VERSION, "s")
    with pytest.raises(SceneError, match=twice):
        JsonTables.load(root / VERSION, "s")


def test_a_damaged_index_is_built_again(dataroot, tmp_path):
    root = _copy(dataroot, tmp_path)
    index = root / VERSION / INDEX_DIR / INDEX_NAME
    index.parent.mkdir()
    index.write_bytes(b"not a database, e.g. a copy cut short")
    tables = open_tables(root / VERSION, "s")
    assert tables.built_here and tables.rows("scene")
