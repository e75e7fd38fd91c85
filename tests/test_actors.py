"""Actors: the scene.json contract, track checks and interpolation, the synthetic street's moving
traffic in its truth renders, and the dynamic masks ingest writes."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from conftest import stage_params

from paradrive import actors as act
from paradrive import geometry
from paradrive.stages.ingest import ingest
from paradrive.scene import READABLE_VERSIONS, load_scene, read_image, write_scene
from paradrive.synthetic import SyntheticStreet
from paradrive.synthetic import raycast as rc

W, H = 320, 192


def box(x: float, y: float, heading: float, z: float = 0.8) -> np.ndarray:
    return act.box_pose([x, y, z], heading)


def car(actor_id: str = "t:car", frames=(0, 1, 2), size=(4.5, 1.9, 1.6), cls: str = "vehicle"):
    poses = [box(2.0 * i, 0.0, 0.0) for i in range(len(frames))]
    return act.Actor(actor_id, cls, True, np.asarray(size, dtype=np.float64),
                     np.asarray(frames, dtype=np.int64), np.stack(poses))


# --------------------------------------------------------------------------- tracks

def test_interpolation_is_linear_in_position_slerp_in_rotation_and_never_extrapolates():
    keys = np.stack([box(0.0, 0.0, 0.0), box(10.0, 4.0, np.pi / 2)])
    inside, poses = act.interpolate_track(np.array([0, 1_000_000]), keys,
                                          np.array([-1, 0, 250_000, 1_000_000, 1_000_001]))
    assert inside.tolist() == [False, True, True, True, False]
    np.testing.assert_allclose(poses[0], keys[0], atol=1e-12)
    np.testing.assert_allclose(poses[2], keys[1], atol=1e-12)
    np.testing.assert_allclose(poses[1][:3, 3], [2.5, 1.0, 0.8], atol=1e-12)
    heading = np.arctan2(poses[1][1, 0], poses[1][0, 0])
    assert heading == pytest.approx(np.pi / 8, abs=1e-12)  # constant angular rate
    assert geometry.is_rigid(poses).all()


BROKEN = [
    ("size", lambda a: setattr(a, "size", np.array([4.5, np.nan, 1.6]))),
    ("size", lambda a: setattr(a, "size", np.array([4.5, 0.0, 1.6]))),
    ("box2world", lambda a: a.box2world.__setitem__((1, 0, 0), np.nan)),
    ("frame 99", lambda a: a.frames.__setitem__(2, 99)),
    ("duplicate", lambda a: a.frames.__setitem__(2, 1)),
    ("class", lambda a: setattr(a, "cls", "spaceship")),
]


@pytest.mark.parametrize("field, breaks", BROKEN, ids=[f"{f}-{i}" for i, (f, _) in enumerate(BROKEN)])
def test_a_broken_actor_is_dropped_with_a_log_line_naming_scene_file_and_field(field, breaks, caplog):
    bad = car("t:bad")
    breaks(bad)
    with caplog.at_level(logging.WARNING, logger="paradrive.actors"):
        kept = act.keep_valid([car("t:good"), bad], range(3), scene_id="s-7", where="labels.json")
    assert [a.id for a in kept] == ["t:good"]
    line = caplog.text
    assert "scene s-7" in line and "labels.json" in line and "t:bad" in line and field in line


def test_scene_json_round_trips_actors_and_schema_1_scenes_without_actors_still_load(tmp_path):
    scene = load_scene_from_uri(tmp_path / "scene", "synthetic:demo?frames=3&width=64&height=48")
    assert scene.actors, "the synthetic street has actors"
    again = load_scene(tmp_path / "scene")
    assert [a.id for a in again.actors] == [a.id for a in scene.actors]
    for a, b in zip(again.actors, scene.actors):
        np.testing.assert_array_equal(a.box2world, b.box2world)
        np.testing.assert_array_equal(a.size, b.size)
        assert (a.cls, a.rigid, a.frames.tolist()) == (b.cls, b.rigid, b.frames.tolist())
    doc = json.loads((tmp_path / "scene" / "scene.json").read_text())
    assert doc["schema_version"] == 2 and 1 in READABLE_VERSIONS
    doc["schema_version"] = 1
    del doc["actors"]
    (tmp_path / "scene" / "scene.json").write_text(json.dumps(doc))
    old = load_scene(tmp_path / "scene")
    assert old.actors == [] and len(old.frames) == 3
    write_scene(old)  # written back in the current schema
    assert json.loads((tmp_path / "scene" / "scene.json").read_text())["schema_version"] == 2


def load_scene_from_uri(folder, uri: str, **params):
    ingest(uri, folder, stage_params("ingest", {"cameras": ["front"], "lidar": False, **params}))
    return load_scene(folder)


# --------------------------------------------------------------------------- masks

def test_box_footprint_is_the_pixels_whose_rays_meet_the_box():
    K = np.array([[100.0, 0, 100.0], [0, 100.0, 100.0], [0, 0, 1]])
    c2w = np.eye(4)  # OpenCV camera at the origin looking down +z
    pose = geometry.make_pose(np.eye(3), [0.0, 0.0, 10.0])  # a 2 m cube, front face at z = 9
    mask = act.box_footprint(pose, (2.0, 2.0, 2.0), c2w, K, 200, 200)
    half = 100.0 / 9.0  # the front face's half-width in pixels
    centres = np.arange(200) + 0.5
    inside = np.abs(centres - 100.0) < half
    np.testing.assert_array_equal(mask, inside[:, None] & inside[None, :])
    behind = act.box_footprint(geometry.make_pose(np.eye(3), [0, 0, -10.0]), (2, 2, 2), c2w, K,
                               200, 200)
    assert not behind.any()
    around = act.box_footprint(geometry.make_pose(np.eye(3), [0, 0, 0.5]), (2, 2, 2), c2w, K,
                               200, 200)
    assert around.all()  # the camera inside a box sees it everywhere


# --------------------------------------------------------------------------- the street

@pytest.fixture(scope="module")
def street():
    return SyntheticStreet(seed=7, frames=30, width=W, height=H, cameras="front")


def mover_of(street, actor_id: str):
    return next(m for m in street.layout.movers if f"synthetic:{m.id}" == actor_id)


def test_the_street_has_oncoming_and_overtaking_cars_crossing_people_and_parked_cars(street):
    actors = street.actors()
    moving = [a for a in actors if act.is_moving(a, 1.0)]
    ego_x = street.ego2world()[:, 0, 3]
    speeds = {}
    for a in moving:
        dx = np.diff(a.centres()[:, 0]) / np.diff(a.frames) * street.fps
        speeds[a.id] = float(np.median(dx))
    assert any(v < 0 for v in speeds.values()), "oncoming cars"
    assert any(v > street.speed_mps + 1 for v in speeds.values()), "cars overtaking the ego"
    assert any(a.cls == "pedestrian" and abs(np.ptp(a.centres()[:, 1])) > 1.0 for a in moving)
    parked = [a for a in actors if not act.is_moving(a, 1.0)]
    assert parked and all(a.cls == "vehicle" for a in parked)
    assert ego_x[-1] > ego_x[0]


def test_a_shifted_truth_view_at_frame_t_shows_each_moving_car_where_its_track_puts_it(street):
    K = street.cameras["front"].K()
    t = 20
    ego = street.ego2world()[t]
    view_c2w = geometry.lateral_shift(street.c2w("front")[t], ego, -2.0)
    w2c = geometry.invert(view_c2w)
    seen = []
    for a in street.actors():
        pose = a.pose_at(t)
        if a.cls != "vehicle" or pose is None or not act.is_moving(a, 1.0):
            continue
        (u, v), z = geometry.project(pose[None, :3, 3], view_c2w, K)[0][0], (w2c @ pose[:, 3])[2]
        if z > 3.0 and 0 <= u < W and 0 <= v < H:
            seen.append((z, a, int(u), int(v)))
    assert seen, "a moving car is in view"
    _, a, u, v = min(seen, key=lambda s: s[0])  # the nearest: nothing stands in front of it
    rows = set(mover_of(street, a.id).rows.tolist())
    world = street.world_at(t)
    hits, _, _ = rc.cast_camera(world.prims, view_c2w, K, W, H, world.bounds)
    assert hits.kind[v, u] == rc.BOX and int(hits.index[v, u]) in rows
    truth = street.render(view_c2w, K, W, H, frames=t)
    depth = float(truth["depth"][0, v, u])
    centre_depth = float((w2c @ a.pose_at(t)[:, 3])[2])
    assert centre_depth - np.linalg.norm(a.size) / 2 <= depth <= centre_depth
    # the same view at another instant: the car has moved on from that pixel
    earlier = street.render(view_c2w, K, W, H, frames=t - 15)
    assert abs(float(earlier["depth"][0, v, u]) - depth) > 1.0


def test_culling_follows_the_actors_to_where_they_are_at_each_frame(street):
    K = street.cameras["front"].K() * [[0.4], [0.4], [1.0]]
    for t in (0, 25):
        world = street.world_at(t)
        pose = geometry.lateral_shift(street.c2w("front")[t], street.ego2world()[t], -3.0)
        fast, _, _ = rc.cast_camera(world.prims, pose, K, 128, 77, world.bounds, cull=True)
        slow, _, _ = rc.cast_camera(world.prims, pose, K, 128, 77, world.bounds, cull=False)
        np.testing.assert_array_equal(fast.t, slow.t)
        np.testing.assert_array_equal(fast.index, slow.index)


def test_ingest_writes_dynamic_masks_of_moving_actors_only(tmp_path):
    frames = 8
    scene = load_scene_from_uri(tmp_path / "scene", f"synthetic:demo?frames={frames}&width={W}&height={H}",
                                moving_threshold_m=1.0)
    street = SyntheticStreet(seed=7, frames=frames, width=W, height=H, cameras="front")
    moving_ids = {a.id for a in scene.actors if act.is_moving(a, 1.0)}
    assert moving_ids and len(moving_ids) < len(scene.actors)
    rows = {kind: set() for kind in ("moving", "parked")}
    for m in street.layout.movers:
        rows["moving" if f"synthetic:{m.id}" in moving_ids else "parked"].update(m.rows.tolist())
    K = street.cameras["front"].K()
    covered = {"moving": [], "parked": []}
    for i in range(frames):
        mask = read_image(tmp_path / "scene" / "masks" / "dynamic" / "front" / f"{i:06d}.png")
        mask = mask[..., 0] > 127
        world = street.world_at(i)
        hits, _, _ = rc.cast_camera(world.prims, street.c2w("front")[i], K, W, H, world.bounds)
        for kind, wanted in rows.items():
            on = (hits.kind == rc.BOX) & np.isin(hits.index, list(wanted))
            covered[kind].append(mask[on])
    moving_px, parked_px = (np.concatenate(covered[k]) for k in ("moving", "parked"))
    assert moving_px.size > 50 and moving_px.all()  # every pixel of a moving actor is masked
    assert parked_px.size > 50 and parked_px.mean() < 0.1  # parked cars mostly are not
