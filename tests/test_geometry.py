"""The lateral shift and the relative pose, as docs/conventions.md defines them (property tests)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from paradrive import geometry as g

angles = st.floats(-np.pi, np.pi, allow_nan=False)
small_angles = st.floats(-0.6, 0.6, allow_nan=False)
coords = st.floats(-500, 500, allow_nan=False)
offsets = st.floats(-6, 6, allow_nan=False).filter(lambda d: abs(d) > 1e-3)


def ego_pose(yaw, pitch, roll, x, y, z):
    rot = g.rotation_about("z", yaw) @ g.rotation_about("y", pitch) @ g.rotation_about("x", roll)
    return g.make_pose(rot, [x, y, z])


def camera_mount(yaw, pitch, height=1.6):
    """cam2ego of a camera yawed/pitched on the roof: OpenCV axes -> ego axes."""
    rot = g.rotation_about("z", yaw) @ g.rotation_about("y", pitch) @ g.OPENCV_TO_FLU
    return g.make_pose(rot, [1.0, 0.0, height])


ego_poses = st.builds(ego_pose, angles, small_angles, small_angles, coords, coords, coords)
mounts = st.builds(camera_mount, angles, small_angles)


@settings(max_examples=200, deadline=None)
@given(ego=ego_poses, mount=mounts, d=offsets)
def test_shift_keeps_every_camera_orientation(ego, mount, d):
    c2w = ego @ mount
    shifted = g.lateral_shift(c2w, ego, d)
    np.testing.assert_allclose(shifted[:3, :3], c2w[:3, :3], atol=1e-12)
    assert g.is_rigid(shifted)


@settings(max_examples=200, deadline=None)
@given(ego=ego_poses, mounts=st.lists(mounts, min_size=2, max_size=5), d=offsets)
def test_shift_moves_every_rig_camera_by_d_along_ego_left(ego, mounts, d):
    left = ego[:3, 1]
    for mount in mounts:
        c2w = ego @ mount
        moved = g.lateral_shift(c2w, ego, d)[:3, 3] - c2w[:3, 3]
        np.testing.assert_allclose(moved, d * left, atol=1e-9)
        assert abs(np.linalg.norm(moved) - abs(d)) < 1e-9


@settings(max_examples=200, deadline=None)
@given(yaw=angles, mount_yaw=angles, mount_pitch=st.floats(-1.2, 1.2), d=offsets,
       x=coords, y=coords)
def test_shift_is_horizontal_for_pitched_and_side_cameras(yaw, mount_yaw, mount_pitch, d, x, y):
    ego = ego_pose(yaw, 0.0, 0.0, x, y, 0.0)  # level vehicle
    c2w = ego @ camera_mount(mount_yaw, mount_pitch)
    moved = g.lateral_shift(c2w, ego, d)[:3, 3] - c2w[:3, 3]
    assert abs(moved[2]) < 1e-9  # no vertical component, however the camera is tilted
    # and it is not the camera's own x axis, unless that happens to be the ego's right axis
    cam_x = c2w[:3, 0]
    if abs(abs(cam_x @ ego[:3, 1]) - 1) > 1e-3:
        assert not np.allclose(moved, -d * cam_x, atol=1e-6)


@settings(max_examples=200, deadline=None)
@given(ego=ego_poses, mount=mounts, d=offsets)
def test_rel_pose_composes_back_to_the_target_pose(ego, mount, d):
    target = ego @ mount
    source = g.lateral_shift(target, ego, d)
    rel = g.relative_pose(target, source)
    np.testing.assert_allclose(target @ rel, source, atol=1e-8)
    # a pure lateral shift: identity rotation, translation of length |d|
    np.testing.assert_allclose(rel[:3, :3], np.eye(3), atol=1e-9)
    assert abs(np.linalg.norm(rel[:3, 3]) - abs(d)) < 1e-8


def test_rel_pose_maps_source_camera_points_into_target_camera():
    ego = ego_pose(0.3, 0.0, 0.0, 10.0, -4.0, 0.0)
    target = ego @ camera_mount(0.0, 0.05)
    source = g.lateral_shift(target, ego, 2.0)
    rel = g.relative_pose(target, source)
    world_point = np.array([20.0, 3.0, 1.0, 1.0])
    in_source = g.invert(source) @ world_point
    in_target = g.invert(target) @ world_point
    np.testing.assert_allclose(rel @ in_source, in_target, atol=1e-9)
    # source is 2 m to the left: for a forward camera that is the target camera's -x side
    assert rel[0, 3] < -1.9


def test_batched_shift_matches_per_frame_shift():
    rng = np.random.default_rng(0)
    egos = np.stack([ego_pose(*rng.uniform(-0.3, 0.3, 3), *rng.uniform(-50, 50, 3)) for _ in range(6)])
    c2w = egos @ camera_mount(0.4, 0.1)
    batched = g.lateral_shift(c2w, egos, -3.0)
    for i in range(6):
        np.testing.assert_allclose(batched[i], g.lateral_shift(c2w[i], egos[i], -3.0))


def test_is_rigid_rejects_nan_scale_and_reflection():
    good = ego_pose(0.1, 0.2, 0.3, 1, 2, 3)
    assert g.is_rigid(good)
    nan = good.copy()
    nan[0, 3] = np.nan
    scaled = good.copy()
    scaled[:3, :3] *= 1.1
    mirrored = good.copy()
    mirrored[:3, 0] *= -1
    assert not g.is_rigid(nan) and not g.is_rigid(scaled) and not g.is_rigid(mirrored)


@settings(max_examples=100, deadline=None)
@given(yaw=angles, pitch=small_angles, roll=small_angles)
def test_quaternion_round_trip(yaw, pitch, roll):
    rot = ego_pose(yaw, pitch, roll, 0, 0, 0)[:3, :3]
    np.testing.assert_allclose(g.quaternion_to_rotation(g.rotation_to_quaternion(rot)), rot,
                               atol=1e-9)


def test_scale_intrinsics_follows_the_resize():
    assert g.scale_intrinsics(1000, 1000, 960, 640, 0.5, 0.25) == (500, 250, 480, 160)


def test_project_matches_pinhole():
    c2w = g.make_pose(np.eye(3), [0, 0, 0])
    K = np.array([[100.0, 0, 50], [0, 100.0, 40], [0, 0, 1]])
    uv, z = g.project(np.array([[1.0, -0.5, 4.0]]), c2w, K)
    np.testing.assert_allclose(uv[0], [50 + 100 * 0.25, 40 - 100 * 0.125])
    assert z[0] == 4.0
