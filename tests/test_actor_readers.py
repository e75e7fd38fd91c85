"""Actors from every log format: a synthetic street with moving traffic, written by the exporters
as Waymo laser labels, nuScenes annotations and DriveStudio instances, ingests to its exact
tracks; broken annotations drop only their actor, with a log line naming scene, file and field."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from conftest import stage_params

from paradrive import actors as act
from paradrive.ingest import export
from paradrive.stages.ingest import ingest
from paradrive.scene import load_scene
from paradrive.synthetic import SyntheticStreet

FRAMES, KEYFRAME_EVERY = 16, 5
PARAMS = stage_params("ingest", {"cameras": ["front"], "lidar": False})


@pytest.fixture(scope="module")
def street():
    # a curved road: headings turn along every track, so rotations are interpolated too
    return SyntheticStreet(seed=7, frames=FRAMES, width=64, height=48, cameras="front",
                           curvature=0.004)


@pytest.fixture(scope="module")
def truth(street):
    return {a.id.split(":", 1)[1]: a for a in street.actors()}


def by_name(scene) -> dict:
    return {a.id.split(":", 1)[1]: a for a in scene.actors}


def assert_exact(found: act.Actor, true: act.Actor) -> None:
    np.testing.assert_array_equal(found.frames, true.frames)
    np.testing.assert_allclose(found.box2world, true.box2world, atol=1e-6)
    np.testing.assert_allclose(found.size, true.size, rtol=0, atol=1e-9)
    assert (found.cls, found.rigid) == (true.cls, true.rigid)


def test_waymo_laser_labels_ingest_to_the_exact_tracks(street, truth, tmp_path):
    path = export.export_waymo(street, tmp_path / "segment-a.tfrecord", lidar=False)
    ingest(f"waymo:{path}", tmp_path / "scene", PARAMS)
    found = by_name(load_scene(tmp_path / "scene"))
    assert set(found) == set(truth)
    for name, true in truth.items():
        assert_exact(found[name], true)
        assert found[name].id == f"waymo:{name}"


def test_drivestudio_instances_ingest_to_the_exact_tracks(street, truth, tmp_path):
    folder = export.export_drivestudio(street, tmp_path / "processed" / "000", lidar=False)
    ingest(f"drivestudio:{folder}", tmp_path / "scene", PARAMS)
    found = by_name(load_scene(tmp_path / "scene"))
    assert set(found) == set(truth)
    for name, true in truth.items():
        assert_exact(found[name], true)


def test_nuscenes_flavour_drivestudio_places_actors_in_its_own_world(street, truth, tmp_path):
    """That flavour's world is the first front-camera pose: seen from the camera, every box is
    where the street puts it."""
    folder = export.export_drivestudio(street, tmp_path / "processed" / "000", flavour="nuscenes",
                                       lidar=False)
    ingest(f"drivestudio:{folder}?fps={street.fps:g}", tmp_path / "scene", PARAMS)
    scene = load_scene(tmp_path / "scene")
    found = by_name(scene)
    assert set(found) == set(truth)
    cam_scene, cam_street = scene.c2w("front"), street.c2w("front")
    for name, a in found.items():
        in_camera = np.linalg.inv(cam_scene[a.frames]) @ a.box2world
        expected = np.linalg.inv(cam_street[a.frames]) @ truth[name].box2world
        np.testing.assert_allclose(in_camera, expected, atol=1e-6)


def export_nuscenes(street, root):
    export.export_nuscenes(street, root, lidar=False, keyframe_every=KEYFRAME_EVERY)
    return f"nuscenes:{root}?version=v1.0-mini#scene-0001"


def test_nuscenes_annotations_interpolate_between_keyframes_and_never_extrapolate(street, truth,
                                                                                  tmp_path):
    ingest(export_nuscenes(street, tmp_path / "nus"), tmp_path / "scene", PARAMS)
    found = by_name(load_scene(tmp_path / "scene"))
    keyframes = np.arange(0, FRAMES, KEYFRAME_EVERY)
    assert found and set(found) <= set(truth)
    worst = 0.0
    for name, a in found.items():
        true = truth[name]
        keyed = np.intersect1d(true.frames, keyframes)
        # frames from the first to the last annotated keyframe: none before, none after
        np.testing.assert_array_equal(a.frames, true.frames[(true.frames >= keyed[0])
                                                             & (true.frames <= keyed[-1])])
        np.testing.assert_allclose(a.size, true.size, rtol=0, atol=1e-9)  # w, l, h converted
        at_key = np.isin(a.frames, keyframes)
        exact = np.stack([true.pose_at(f) for f in a.frames])
        np.testing.assert_allclose(a.box2world[at_key], exact[at_key], atol=1e-6)
        worst = max(worst, float(np.abs(a.box2world - exact).max()))
    # between keyframes: constant speed along a 250 m radius, chords of at most 6 m, and people
    # who stop at the kerb (at most 1.6 m/s x 0.5 s off)
    assert 0.0 < worst < 0.8
    moving = [a for a in found.values() if act.is_moving(a, 1.0)]
    assert moving and all(a.size[0] >= a.size[1] for a in moving if a.cls == "vehicle")


def log_says(caplog, *words: str) -> None:
    lines = [r.getMessage() for r in caplog.records if r.name == "paradrive.actors"]
    assert any(all(w in line for w in words) for line in lines), lines


def rewrite(path, change) -> None:
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def test_broken_nuscenes_annotations_drop_their_actor_only(street, truth, tmp_path, caplog):
    uri = export_nuscenes(street, tmp_path / "nus")
    meta = tmp_path / "nus" / "v1.0-mini"
    rows = json.loads((meta / "sample_annotation.json").read_text())
    cars = sorted({r["instance_token"] for r in rows if r["instance_token"].startswith("car")})
    bad_size, bad_sample, bad_category = cars[:3]

    def damage(doc):
        for r in doc:
            if r["instance_token"] == bad_size:
                r["size"] = [1.9, -4.5, 1.6]
        next(r for r in doc if r["instance_token"] == bad_sample)["sample_token"] = "no-such-sample"

    rewrite(meta / "sample_annotation.json", damage)
    rewrite(meta / "category.json", lambda doc: doc.append(
        {"token": "odd", "name": "vehicle.spaceship", "description": ""}))
    rewrite(meta / "instance.json", lambda doc: next(
        i for i in doc if i["token"] == bad_category).__setitem__("category_token", "odd"))
    with caplog.at_level(logging.WARNING, logger="paradrive.actors"):
        ingest(uri, tmp_path / "scene", PARAMS)
    found = by_name(load_scene(tmp_path / "scene"))
    assert not {bad_size, bad_sample, bad_category} & set(found)
    assert len(found) > 5
    sid = "scene " + (tmp_path / "scene").name
    log_says(caplog, sid, "sample_annotation.json", bad_size, "size")
    log_says(caplog, sid, "sample_annotation.json", bad_sample, "no-such-sample")
    log_says(caplog, sid, bad_category, "vehicle.spaceship", "category")


def test_broken_drivestudio_instances_drop_their_actor_only(street, tmp_path, caplog):
    folder = export.export_drivestudio(street, tmp_path / "processed" / "000", lidar=False)
    info_path = folder / "instances" / "instances_info.json"
    info = json.loads(info_path.read_text())
    keys = sorted(info, key=int)
    nan_heading, missing_frame, twice, unknown = keys[:4]
    info[nan_heading]["frame_annotations"]["obj_to_world"][0][0][0] = float("nan")
    info[missing_frame]["frame_annotations"]["frame_idx"][-1] = 999
    info[unknown]["class_name"] = "Hovercraft"
    info_path.write_text(json.dumps(info))
    frame = str(info[twice]["frame_annotations"]["frame_idx"][0])
    rewrite(folder / "instances" / "frame_instances.json",
            lambda doc: doc[frame].append(int(twice)))
    with caplog.at_level(logging.WARNING, logger="paradrive.actors"):
        ingest(f"drivestudio:{folder}", tmp_path / "scene", PARAMS)
    found = {a.id for a in load_scene(tmp_path / "scene").actors}
    dropped = {f"drivestudio:{info[k]['id']}" for k in (nan_heading, missing_frame, unknown)}
    assert not dropped & found and f"drivestudio:{twice}" not in found
    assert len(found) == len(info) - 4
    sid = "scene " + (tmp_path / "scene").name
    log_says(caplog, sid, "instances_info.json", info[nan_heading]["id"], "box2world")
    log_says(caplog, sid, "instances_info.json", "frame_idx 999")
    log_says(caplog, sid, "frame_instances.json", "duplicate")
    log_says(caplog, sid, "Hovercraft")


def test_broken_waymo_labels_drop_their_actor_only(street, tmp_path, caplog):
    src = export.source_from_street(street)
    good = src.actors
    nan_size = act.Actor("synthetic:nan-size", "vehicle", True, np.array([4.0, np.nan, 1.5]),
                         good[0].frames.copy(), good[0].box2world.copy())
    twice = good[1]
    src.actors = [*good, nan_size, twice]  # the second copy: two boxes with one id per frame
    path = export.export_waymo(src, tmp_path / "segment-b.tfrecord", lidar=False)
    with caplog.at_level(logging.WARNING, logger="paradrive.actors"):
        ingest(f"waymo:{path}", tmp_path / "scene", PARAMS)
    found = {a.id for a in load_scene(tmp_path / "scene").actors}
    assert len(found) == len(good) - 1
    assert "waymo:nan-size" not in found and f"waymo:{twice.id.split(':')[1]}" not in found
    sid = "scene " + (tmp_path / "scene").name
    log_says(caplog, sid, "segment-b.tfrecord", "nan-size", "size")
    log_says(caplog, sid, "segment-b.tfrecord", "duplicate")
