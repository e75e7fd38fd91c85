"""A scene's footprint: its bytes by top folder, and ``paradrive build`` printing it at the end."""

from __future__ import annotations

import uuid

from typer.testing import CliRunner

from paradrive.cli import app
from paradrive.pipeline.budget import scene_footprint
from paradrive.storage import DataRoot

SCENE_ID = "synthetic-demo-s7"
FILES = {"scene.json": 10, "images/front/000000.jpg": 100, "images/front/000001.jpg": 120,
         "lidar/000000.npy": 300, "gs/ckpt_000100.ply": 1000, "gs/fit.json": 20,
         "renders/front/target/000000.png": 250, "renders/renders.json": 5,
         "clips/front/front/target.mp4": 700, ".paradrive/clip.json": 3}


def write_scene(folder) -> None:
    for rel, size in FILES.items():
        path = folder / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"x" * size)


def test_footprint_sums_bytes_by_top_folder(tmp_path):
    write_scene(tmp_path / "data" / "scenes" / SCENE_ID)
    assert scene_footprint(tmp_path / "data", SCENE_ID) == {
        "images": 220, "lidar": 300, "masks": 0, "gs": 1020, "renders": 255, "clips": 700,
        "other": 13}


def test_footprint_of_a_url_root_is_listed_remotely(tmp_path):
    local = tmp_path / "data"
    write_scene(local / "scenes" / SCENE_ID)
    root = DataRoot.of(f"memory://footprint-{uuid.uuid4().hex[:8]}/data", cache_dir=str(tmp_path / "cache"))
    fs, base = root.filesystem()
    fs.put(str(local / "scenes" / SCENE_ID), f"{base}/scenes/{SCENE_ID}", recursive=True)
    assert scene_footprint(root, SCENE_ID) == scene_footprint(local, SCENE_ID)


def test_build_prints_each_scene_footprint(tmp_path, monkeypatch):
    import pipeline_stages
    from paradrive.commands import common

    monkeypatch.setattr(common.out, "width", 200)   # one line a row, as on a wide terminal
    monkeypatch.setenv("PARADRIVE_STAGES", str(pipeline_stages.write_stages(tmp_path / "stages")))
    args = ["build", "--scene", "synthetic:demo?seed=7", "--scene", "synthetic:demo?seed=8",
            "--data", str(tmp_path / "data"), "--manifests", str(tmp_path / "m"),
            "--stages", "ingest,fit,render,clip"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    table = result.output[result.output.index("footprint (MB)"):]
    header = table.splitlines()[2]
    assert header.replace("┃", " ").split() == [
        "scene", "images", "lidar", "masks", "gs", "renders", "clips", "other", "total"]
    assert "synthetic-demo-s7" in table and "synthetic-demo-s8" in table and "all 2 scenes" in table
