"""``paradrive view``: a scene or a build written as a Rerun recording, read back with rerun's own
reader and checked with ``rerun rrd verify``: the entities, timelines and counts it promises
(cameras, frames, LiDAR points, actors, checkpoints, videos, pairs) match the scene or build."""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from packaging.requirements import Requirement

from paradrive import view
from paradrive.contracts.layout import SceneLayout
from paradrive.contracts.records import ClipsRecord, FitRecord, RendersRecord
from paradrive.errors import ConfigError, ParaDriveError
from paradrive.pairs import read_pairs
from paradrive.scene import load_scene

rr = pytest.importorskip("rerun")
REPO = Path(__file__).resolve().parents[1]
SCENE_ID = "synthetic-demo-s7"


@dataclass
class Entity:
    """What a recording holds at one entity path: component columns (static and on timelines),
    the ``frame`` values of its rows, and its rows' Arrow columns."""

    static: dict[str, list] = field(default_factory=lambda: defaultdict(list))
    temporal: dict[str, list] = field(default_factory=lambda: defaultdict(list))
    frames: list[int] = field(default_factory=list)
    timelines: set[str] = field(default_factory=set)


def read_recording(path: Path) -> dict[str, Entity]:
    """Every entity of an .rrd file, by path, as rerun's reader returns its chunks."""
    from rerun.chunk import RrdReader

    found: dict[str, Entity] = defaultdict(Entity)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        entity = found[chunk.entity_path]
        entity.timelines.update(chunk.timeline_names)
        if "frame" in chunk.timeline_names:
            entity.frames += batch.column("frame").to_pylist()
        into = entity.static if chunk.is_static else entity.temporal
        for name in batch.schema.names:
            if ":" in name:   # components are <Archetype>:<field>
                into[name] += batch.column(name).to_pylist()
    return dict(found)


def verify(path: Path) -> None:
    """``rerun rrd verify`` (the CLI rerun-sdk ships) accepts the file."""
    done = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(path)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]


def part(name: str) -> str:
    return str(rr.escape_entity_path_part(name))


def points(entity: Entity, column: str = "Points3D:positions", static: bool = True) -> int:
    rows = (entity.static if static else entity.temporal)[column]
    return sum(len(r) for r in rows)


@pytest.fixture(scope="module")
def scene_recording(smoke_build, tmp_path_factory):
    """Seed 7 of the smoke build (every stage done), viewed through the command line."""
    out = tmp_path_factory.mktemp("view") / "scene.rrd"
    scene_dir = SceneLayout.of(smoke_build["data_dir"], SCENE_ID).root
    done = subprocess.run([sys.executable, "-m", "paradrive.cli", "view", str(scene_dir), "--save", str(out)],
                          capture_output=True, text=True, cwd=REPO, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"wrote {out}" in done.stdout
    return {"path": out, "entities": read_recording(out), "layout": SceneLayout(scene_dir),
            "scene": load_scene(scene_dir)}


def test_a_scene_recording_passes_rerun_verify(scene_recording):
    verify(scene_recording["path"])


def test_every_camera_has_its_pose_pinhole_image_and_masks_on_every_frame(scene_recording):
    scene, entities = scene_recording["scene"], scene_recording["entities"]
    frames = sorted(f.index for f in scene.frames)
    assert len(scene.cameras) == 3
    for name, cam in scene.cameras.items():
        pose, image = entities[f"/world/cameras/{part(name)}"], entities[f"/world/cameras/{part(name)}/image"]
        assert sorted(pose.frames) == frames and {"frame", "time"} <= pose.timelines
        c2w = scene.frames[5].cameras[name].c2w
        assert np.allclose(pose.temporal["Transform3D:translation"][5], c2w[:3, 3], atol=1e-5)
        assert image.static["Pinhole:resolution"] == [[[cam.width, cam.height]]]
        assert len(image.temporal["EncodedImage:blob"]) == len(frames)
        assert image.temporal["EncodedImage:media_type"][0] == ["image/jpeg"]
        for mask in ("sky", "dynamic"):
            assert sorted(entities[f"/world/cameras/{part(name)}/image/{mask}"].frames) == frames
    ego = entities["/world/ego_path"].static["LineStrips3D:strips"][0][0]
    assert len(ego) == len(frames)


def test_the_lidar_points_of_every_frame_are_there(scene_recording):
    scene, lidar = scene_recording["scene"], scene_recording["entities"]["/world/lidar"]
    expected = [len(scene.lidar_frame(p)) for p in range(len(scene.frames))]
    assert sorted(lidar.frames) == [f.index for f in scene.frames]
    assert [len(r) for r in lidar.temporal["Points3D:positions"]] == expected


def test_every_actor_has_a_labelled_box_that_follows_its_track(scene_recording):
    scene, entities = scene_recording["scene"], scene_recording["entities"]
    assert len(scene.actors) > 5
    for actor in scene.actors:
        entity = f"/world/actors/{part(actor.id)}"
        assert sorted(f for f in entities[entity].frames if f in set(actor.frames.tolist())) == \
            sorted(actor.frames.tolist())
        box = entities[f"{entity}/box"]
        assert box.temporal["Boxes3D:labels"][0] == [f"{actor.id} ({actor.cls})"]
        assert np.allclose(box.temporal["Boxes3D:half_sizes"][0][0], 0.5 * actor.size)
    short = [a for a in scene.actors if a.frames.max() < scene.frames[-1].index]
    assert short, "the smoke scene has an actor that leaves before the end"
    cleared = entities[f"/world/actors/{part(short[0].id)}"].temporal["Clear:is_recursive"]
    assert cleared and cleared == [[True]] * len(cleared)


def test_every_checkpoint_is_there_as_points_and_the_actor_nodes_ride_their_boxes(scene_recording):
    from paradrive.gs.ply import load_ply

    layout, entities = scene_recording["layout"], scene_recording["entities"]
    fit = FitRecord.load(layout.fit_json)
    for ckpt in fit.checkpoints:
        entity = f"/world/gaussians/ckpt_{ckpt.iteration:06d}"
        n = len(load_ply(layout.checkpoint(ckpt.iteration))["means"])
        assert n < view.MAX_GAUSSIANS
        assert points(entities[entity]) + points(entities[f"{entity}/sky"]) == n
        assert points(entities[f"{entity}/sky"]) > 0   # the fit's sky shell, apart
    assert fit.actors
    last = fit.at(None).iteration
    for node in fit.actors:
        n = len(load_ply(layout.actor_checkpoint(last, node.file))["means"])
        assert points(entities[f"/world/actors/{part(node.id)}/gaussians"], static=False) >= n


def test_the_rendered_streams_have_their_cameras_and_the_clips_are_videos(scene_recording):
    layout, entities = scene_recording["layout"], scene_recording["entities"]
    renders, clips = RendersRecord.load(layout.renders_json), ClipsRecord.load(layout.clips_json)
    for camera, rendered in renders.cameras.items():
        for name, stream in rendered.streams.items():
            pose = entities[f"/world/renders/{part(camera)}/{part(name)}"]
            assert len(pose.frames) == len(rendered.frames)
            assert np.allclose(pose.temporal["Transform3D:translation"][-1],
                               np.asarray(stream.c2w[-1]).reshape(4, 4)[:3, 3], atol=1e-5)
    videos = 0
    for clip in clips.clips:
        for name, stream in clip.streams.items():
            entity = entities[f"/world/renders/{part(clip.camera)}/{part(name)}/image/{part(clip.clip)}"]
            assert bytes(entity.static["AssetVideo:blob"][0][0]) == (layout.root / stream.file).read_bytes()
            assert sorted(entity.frames)[:clip.num_frames] == clip.frame_indices
            assert len(entity.temporal["VideoFrameReference:timestamp"]) == clip.num_frames
            videos += 1
    assert videos == 36   # 3 clips x 12 streams


@pytest.fixture(scope="module")
def build_recording(smoke_build, tmp_path_factory):
    out = tmp_path_factory.mktemp("view") / "build.rrd"
    report = view.view_build(smoke_build["build_dir"], out)
    return {"path": out, "report": report, "entities": read_recording(out)}


def test_a_build_recording_passes_rerun_verify(build_recording):
    verify(build_recording["path"])


def test_every_pair_has_its_three_videos_both_cameras_and_its_scores(build_recording, smoke_build):
    entities = build_recording["entities"]
    rows = read_pairs(smoke_build["build_dir"]).to_pylist()
    assert build_recording["report"].counts["pairs"] == len(rows) == 144
    uris = {r[c] for r in rows for c in ("source_uri", "condition_uri", "target_uri")}
    assert len([e for e in entities if e.startswith("/media/")]) == len(uris)
    for row in rows[::37]:
        base = "/pairs/" + "/".join(part(p) for p in row["pair_id"].split("/"))
        for role in ("source/image", "condition", "target/image"):
            refs = entities[f"{base}/{role}"]
            assert sorted(refs.frames) == row["frame_indices"]
            (asset,) = refs.static["VideoFrameReference:video_reference"]
            uri = row[f"{role.partition('/')[0]}_uri"]
            assert asset == ["/".join(part(p) for p in uri.split("/"))]
        target = np.asarray(row["target_c2w"]).reshape(-1, 4, 4)
        source = target @ np.asarray(row["rel_pose"], dtype=np.float64).reshape(-1, 4, 4)
        for role, c2w in (("target", target), ("source", source)):
            moved = np.asarray(entities[f"{base}/{role}"].temporal["Transform3D:translation"]).reshape(-1, 3)
            assert np.allclose(moved, c2w[:, :3, 3], atol=1e-4)
        (text,) = entities[f"{base}/scores"].static["TextDocument:text"][0]
        assert f"{row['condition_psnr']:.2f} dB" in text and row["pair_id"] in text


def test_one_pair_is_viewed_through_the_command_line(smoke_build, tmp_path):
    pair_id = read_pairs(smoke_build["build_dir"], ["pair_id"]).column("pair_id")[5].as_py()
    out = tmp_path / "pair.rrd"
    done = subprocess.run([sys.executable, "-m", "paradrive.cli", "view", str(smoke_build["build_dir"]),
                           "--pair", pair_id, "--save", str(out)], capture_output=True, text=True, cwd=REPO,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    pairs = {e.rsplit("/", 1)[0] for e in read_recording(out) if e.endswith("/scores")}
    assert pairs == {"/pairs/" + "/".join(part(p) for p in pair_id.split("/"))}
    verify(out)


def test_an_unknown_pair_is_named_and_nothing_is_written(smoke_build, tmp_path):
    with pytest.raises(ConfigError, match="no pair 'synthetic/nope' in this build"):
        view.view_build(smoke_build["build_dir"], tmp_path / "x.rrd", pair_ids=["synthetic/nope"])
    assert list(tmp_path.iterdir()) == []


def test_a_scene_after_ingest_alone_is_found_by_its_uri_and_shows_what_ingest_wrote(tiny_scene, tmp_path):
    kind, folder = view.resolve_target("synthetic:demo?seed=7", tiny_scene.parent.parent)
    assert (kind, folder) == ("scene", tiny_scene)
    report = view.view_scene(folder, tmp_path / "tiny.rrd")
    entities = read_recording(report.path)
    assert report.counts["frames"] == 8 and report.counts["lidar_frames"] == 8
    assert len(entities["/world/cameras/" + part("front") + "/image"].temporal["EncodedImage:blob"]) == 8
    assert not [e for e in entities if e.startswith(("/world/gaussians", "/world/renders"))]
    assert view.default_output(folder) == folder.parent / f"{folder.name}.rrd"


def test_a_folder_that_is_neither_scene_nor_build_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="neither scene.json"):
        view.resolve_target(str(tmp_path), tmp_path)
    with pytest.raises(ConfigError, match="ingest it first"):
        view.resolve_target("synthetic:demo?seed=99", tmp_path)


def test_without_rerun_the_error_names_the_fix(monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)   # what an import finds when it is not installed
    with pytest.raises(ParaDriveError, match=r'pip install "paradrive\[view\]"'):
        view.require_rerun()


def test_spawn_without_a_display_says_how_to_open_the_file(monkeypatch, tmp_path):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(ParaDriveError, match="no display") as caught:
        view.open_viewer(tmp_path / "a.rrd")
    assert f"rerun {tmp_path / 'a.rrd'}" in str(caught.value)


def test_rerun_is_an_extra_that_the_view_module_imports_only_to_write():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    assert [Requirement(r).name for r in project["optional-dependencies"]["view"]] == ["rerun-sdk"]
    assert "paradrive[view]" in project["optional-dependencies"]["test"]
    assert not any(Requirement(r).name == "rerun-sdk" for r in project["dependencies"])
    tree = ast.parse((REPO / "paradrive" / "view.py").read_text())
    top = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
    modules = [a.name for n in top if isinstance(n, ast.Import) for a in n.names]
    modules += [n.module or "" for n in top if isinstance(n, ast.ImportFrom)]
    assert not [m for m in modules if m.partition(".")[0] == "rerun"]
