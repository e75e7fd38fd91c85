"""The synthetic street: deterministic, exact depth, true shifted views, LiDAR on surfaces."""

import numpy as np
import pytest

from paradrive.synthetic import CameraSpec, SyntheticStreet
from paradrive.synthetic import street as street_mod

W, H = 160, 96


def shift_left(street: SyntheticStreet, frame: int, c2w: np.ndarray, d: float) -> np.ndarray:
    """c2w of the same camera with the vehicle moved d metres to its left (docs/conventions.md)."""
    ego = street.ego2world()[frame]
    move = np.eye(4)
    move[1, 3] = d
    return ego @ move @ np.linalg.inv(ego) @ c2w


def pixel_rays(c2w: np.ndarray, K: np.ndarray, width: int, height: int):
    """World directions (H, W, 3) with unit camera-z through pixel centres (u + 0.5, v + 0.5)."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    return cam @ c2w[:3, :3].T


def back_project(c2w, K, depth):
    d = pixel_rays(c2w, K, depth.shape[1], depth.shape[0])
    return c2w[:3, 3] + depth[..., None] * d


def project(c2w, K, X):
    pc = np.linalg.inv(c2w) @ np.append(X, 1.0)
    return K[0, 0] * pc[0] / pc[2] + K[0, 2], K[1, 1] * pc[1] / pc[2] + K[1, 2], pc[2]


@pytest.fixture(scope="module")
def street():
    return SyntheticStreet(seed=7, frames=20, width=W, height=H)


@pytest.fixture(scope="module")
def frame0(street):
    return street.render_frame("front", 0)


def test_same_seed_gives_the_same_street_and_pixels(street, frame0):
    again = SyntheticStreet(seed=7, frames=20, width=W, height=H)
    np.testing.assert_array_equal(again.layout.boxes, street.layout.boxes)
    view = again.render_frame("front", 0)
    np.testing.assert_array_equal(view["rgb"], frame0["rgb"])
    np.testing.assert_array_equal(view["depth"], frame0["depth"])


def test_longer_street_keeps_the_layout_of_a_shorter_one():
    short = SyntheticStreet(seed=7, frames=20, width=W, height=H)
    long = SyntheticStreet(seed=7, frames=120, width=W, height=H)
    for field in ("boxes", "cylinders", "spheres"):
        assert {tuple(b) for b in getattr(short.layout, field)} <= {
            tuple(b) for b in getattr(long.layout, field)}
    a, b = short.render_frame("front", 3), long.render_frame("front", 3)
    near = a["depth"] < 100.0  # the longer street goes on where the shorter one ends
    assert near.mean() > 0.5
    np.testing.assert_array_equal(a["rgb"][near], b["rgb"][near])


def test_different_seeds_give_different_streets(frame0):
    other = SyntheticStreet(seed=8, frames=20, width=W, height=H)
    assert other.layout.boxes.shape != (0, 6)
    assert np.mean(other.render_frame("front", 0)["rgb"] != frame0["rgb"]) > 0.2


def test_poses_timestamps_and_render_shapes(street):
    ego = street.ego2world()
    assert ego.shape == (20, 4, 4) and ego.dtype == np.float64
    np.testing.assert_allclose(ego[0], np.eye(4), atol=1e-12)
    np.testing.assert_allclose(ego[5, :3, 3], [street.speed_mps * 5 / street.fps, 0, 0])
    stamps = street.timestamps_us()
    assert stamps.dtype == np.int64 and stamps[0] == 0 and stamps[3] == 300_000
    spec = street.cameras["front"]
    assert isinstance(spec, CameraSpec) and (spec.width, spec.height) == (W, H)
    np.testing.assert_allclose(street.c2w("front"), ego @ spec.cam2ego)
    hfov = np.rad2deg(2 * np.arctan(0.5 * W / spec.fx))
    assert 69 < hfov < 71
    views = street.render(street.c2w("front")[:2], spec.K(), 64, 48)
    assert views["rgb"].shape == (2, 48, 64, 3) and views["rgb"].dtype == np.uint8
    assert views["depth"].shape == (2, 48, 64) and views["depth"].dtype == np.float32
    assert views["sky"].shape == (2, 48, 64) and views["sky"].dtype == bool
    single = street.render(street.c2w("front")[1], spec.K(), 64, 48)
    np.testing.assert_array_equal(single["rgb"][0], views["rgb"][1])


def test_front_camera_looks_forward_slightly_down_from_the_roof(street):
    cam2ego = street.cameras["front"].cam2ego
    rot = cam2ego[:3, :3]
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.isclose(np.linalg.det(rot), 1.0)
    forward = rot[:, 2]
    assert forward[0] > 0.99 and abs(forward[1]) < 1e-12
    assert np.isclose(np.rad2deg(np.arcsin(-forward[2])), 3.0)
    np.testing.assert_allclose(cam2ego[:3, 3], [1.5, 0.0, 1.6])
    np.testing.assert_allclose(rot[:, 0], [0, -1, 0], atol=1e-12)  # image right = ego right


def test_side_cameras_are_yawed_45_degrees():
    rig = SyntheticStreet(frames=2, width=W, height=H, cameras="front,front_left,front_right")
    for name, sign in (("front_left", 1), ("front_right", -1)):
        fwd = rig.cameras[name].cam2ego[:3, 2]
        assert np.isclose(np.rad2deg(np.arctan2(fwd[1], fwd[0])), 45.0 * sign)
    view = rig.render_frame("front_left", 1)
    assert view["rgb"].shape == (H, W, 3)


def test_road_depth_is_the_exact_ray_plane_intersection(street, frame0):
    c2w = street.c2w("front")[0]
    K = street.cameras["front"].K()
    rays = pixel_rays(c2w, K, W, H)
    o = c2w[:3, 3]
    # the bottom rows look at the road just ahead of the car
    t_plane = -o[2] / rays[-10:, :, 2]
    np.testing.assert_allclose(frame0["depth"][-10:], t_plane, rtol=1e-6)
    pts = back_project(c2w, K, frame0["depth"].astype(np.float64))
    assert np.abs(pts[-10:, :, 2]).max() < 1e-4


def test_lane_marking_lies_where_the_pinhole_model_projects_it():
    street = SyntheticStreet(seed=7, frames=2, width=416, height=240)
    view = street.render_frame("front", 0)
    c2w = street.c2w("front")[0]
    K = street.cameras["front"].K()
    lw = street.layout.lane_w
    grey = view["rgb"].astype(float).mean(-1)

    def at(X):
        u, v, z = project(c2w, K, np.asarray(X, float))
        return int(np.floor(v)), int(np.floor(u)), z

    # the dash of the left lane divider spans s in [9, 12], |l - lw/2| < 0.075
    for X in ([10.5, lw / 2, 0.0], [11.0, lw / 2 + 0.03, 0.0], [9.5, lw / 2 - 0.03, 0.0]):
        r, c, z = at(X)
        assert grey[r, c] > 150, X  # paint
        assert abs(view["depth"][r, c] - z) / z < 0.02
    for X in ([13.5, lw / 2, 0.0], [7.5, lw / 2, 0.0], [10.5, lw / 2 + 0.35, 0.0]):
        r, c, _ = at(X)
        assert grey[r, c] < 110, X  # asphalt around it


def first_visible_car_rear(street, c2w, K, depth, row_of):
    """A parked car on the right whose rear face shows in the view, and that face's pixels."""
    L = street.layout
    cars = np.flatnonzero((L.box_mat == street_mod.CAR) & (L.boxes[:, 3] < 0) & (L.boxes[:, 0] > 8))
    for i in cars[np.argsort(L.boxes[cars, 0])]:
        s0, _, l0, l1, z0, z1 = L.boxes[i]
        X = np.array([s0, l1, 0.5 * (z0 + z1)])
        u, v, z = project(c2w, K, X)
        if not (0 <= u < depth.shape[1] and 0 <= v < depth.shape[0]):
            continue
        row = int(np.floor(v))
        pts = back_project(c2w, K, depth.astype(np.float64))[row]
        on = (np.abs(pts[:, 0] - s0) < 1e-3) & (pts[:, 1] > l0 - 1e-3) & (pts[:, 1] < l1 + 1e-3)
        if on.sum() >= 3:
            return i, X, row, np.flatnonzero(on)
    return None


def test_shifting_two_metres_left_moves_a_roadside_edge_by_fx_d_over_z():
    street = SyntheticStreet(seed=7, frames=2, width=416, height=240)
    K = street.cameras["front"].K()
    c2w = street.c2w("front")[0]
    shifted = shift_left(street, 0, c2w, 2.0)
    np.testing.assert_allclose(shifted[:3, 3] - c2w[:3, 3], [0, 2, 0], atol=1e-12)
    views = street.render(np.stack([c2w, shifted]), K, 416, 240)
    found = first_visible_car_rear(street, c2w, K, views["depth"][0], None)
    assert found is not None, "no parked car rear visible on the right"
    i, X, row, cols = found
    u0, v0, z0 = project(c2w, K, X)
    u1, v1, z1 = project(shifted, K, X)
    # pinhole prediction: same row and depth, u moves right by fx * d / z
    assert np.isclose(v1, v0) and np.isclose(z1, z0)
    assert np.isclose(u1 - u0, K[0, 0] * 2.0 / z0)
    s0, _, l0, l1, _, _ = street.layout.boxes[i]
    face_depth = []
    for view_i, u_edge, pose in ((0, u0, c2w), (1, u1, shifted)):
        pts = back_project(pose, K, views["depth"][view_i].astype(np.float64))[row]
        on = np.flatnonzero((np.abs(pts[:, 0] - s0) < 1e-3) & (pts[:, 1] > l0 - 1e-3)
                            & (pts[:, 1] < l1 + 1e-3))
        assert len(on) >= 3
        # the inner edge (nearest the road) is the face's leftmost column, unoccluded
        assert abs(on.min() + 0.5 - u_edge) <= 1.0
        # the face is a plane of constant depth along the row, the same from both poses
        np.testing.assert_allclose(views["depth"][view_i][row, on], views["depth"][view_i][row, on[0]],
                                   rtol=1e-6)
        face_depth.append(views["depth"][view_i][row, on[0]])
    np.testing.assert_allclose(face_depth[1], face_depth[0], rtol=1e-6)
    np.testing.assert_allclose(face_depth[0], z0, rtol=1e-3)


def test_sky_mask_is_exactly_where_depth_is_infinite(frame0):
    sky = frame0["sky"]
    assert sky.any() and not sky.all()
    np.testing.assert_array_equal(sky, ~np.isfinite(frame0["depth"]))
    assert (frame0["depth"][~sky] > 0).all()
    blue = frame0["rgb"][sky].astype(int)
    assert (blue[:, 2] >= blue[:, 0]).mean() > 0.95
    assert not sky[-H // 3:].any()  # the lower image is road


def test_lidar_points_lie_on_the_rendered_surfaces():
    street = SyntheticStreet(seed=7, frames=10, width=416, height=240, lidar=True, traffic=False)
    pts = street.lidar_points(4).astype(np.float64)
    assert pts.ndim == 2 and pts.shape[1] == 3 and len(pts) > 5000
    assert street.lidar_points(4).dtype == np.float32
    ego = street.ego2world()[4]
    origin = ego[:3, 3] + [0, 0, street_mod.LIDAR_HEIGHT]
    assert np.linalg.norm(pts - origin, axis=1).max() <= street_mod.LIDAR_MAX_RANGE + 1e-3
    ground = (np.abs(pts[:, 1]) < street.layout.edge_l) & (pts[:, 2] < 0.05)
    assert ground.sum() > 1000 and np.abs(pts[ground, 2]).max() < 1e-4
    c2w = street.c2w("front")[4]
    K = street.cameras["front"].K()
    depth = street.render_frame("front", 4)["depth"]
    pc = (pts - c2w[:3, 3]) @ c2w[:3, :3]
    ahead = pc[:, 2] > 2.0
    u = K[0, 0] * pc[ahead, 0] / pc[ahead, 2] + K[0, 2]
    v = K[1, 1] * pc[ahead, 1] / pc[ahead, 2] + K[1, 2]
    inside = (u >= 0) & (u < 416) & (v >= 0) & (v < 240)
    rendered = depth[v[inside].astype(int), u[inside].astype(int)]
    rel = np.abs(rendered - pc[ahead, 2][inside]) / pc[ahead, 2][inside]
    assert inside.sum() > 1000
    assert np.mean(rel < 0.03) > 0.9


def on_some_surface(street, pts, tol=1e-4, frame=0):
    """Whether world points lie on the boundary of a road box (where it is at ``frame``),
    cylinder or sphere, or the ground."""
    s, l = street.arc.to_road(pts[:, 0], pts[:, 1])
    z = pts[:, 2]
    L = street.layout
    ok = np.abs(z) < tol
    ok |= np.abs(z - street_mod.KERB_H) < tol
    ok |= (np.abs(np.abs(l) - L.kerb_l) < tol) & (z < street_mod.KERB_H + tol)
    for s0, s1, l0, l1, z0, z1 in street.world_at(frame).layout.boxes:
        inside = ((s > s0 - tol) & (s < s1 + tol) & (l > l0 - tol) & (l < l1 + tol)
                  & (z > z0 - tol) & (z < z1 + tol))
        # s is an arc length on the centreline: a tolerance in metres at offset l scales by it
        k = street.arc.kappa
        scale = abs(1 - k * l)
        bound = (np.minimum(np.abs(s - s0), np.abs(s - s1)) * scale < tol) | (
            np.minimum(np.abs(l - l0), np.abs(l - l1)) < tol) | (
            np.minimum(np.abs(z - z0), np.abs(z - z1)) < tol)
        ok |= inside & bound
    for cx, cy, r, z0, z1 in L.cylinders:
        rr = np.hypot(pts[:, 0] - cx, pts[:, 1] - cy)
        ok |= (np.abs(rr - r) < tol) & (z > z0 - tol) & (z < z1 + tol)
        ok |= (rr < r + tol) & (np.abs(z - z1) < tol)
    for cx, cy, cz, r in L.spheres:
        ok |= np.abs(np.linalg.norm(pts - [cx, cy, cz], axis=1) - r) < tol
    return ok


def test_curved_street_bends_the_trajectory_and_depth_stays_exact():
    kappa = 0.004
    street = SyntheticStreet(seed=11, frames=60, width=W, height=H, curvature=kappa)
    ego = street.ego2world()
    heading = np.arctan2(ego[:, 1, 0], ego[:, 0, 0])
    s = street.speed_mps * np.arange(60) / street.fps
    np.testing.assert_allclose(heading, kappa * s, atol=1e-12)
    # the path is a circle of radius 1/kappa about (0, 1/kappa)
    np.testing.assert_allclose(np.hypot(ego[:, 0, 3], ego[:, 1, 3] - 1 / kappa), 1 / kappa)
    assert heading[-1] > np.deg2rad(10)
    for frame in (0, 59):
        view = street.render_frame("front", frame)
        assert view["sky"].any() and (~view["sky"]).any()
        c2w = street.c2w("front")[frame]
        pts = back_project(c2w, street.cameras["front"].K(), view["depth"].astype(np.float64))
        near = np.isfinite(view["depth"]) & (view["depth"] < 60)
        p = pts[near]
        # float32 depth: the point is within a few ulps of depth along the ray
        tol = 1e-6 * view["depth"][near].max() * 8 + 1e-4
        assert np.mean(on_some_surface(street, p, tol, frame)) > 0.995


def test_shifted_curved_view_renders_and_keeps_the_sky_up():
    street = SyntheticStreet(seed=3, frames=40, width=W, height=H, curvature=-0.006)
    c2w = street.c2w("front")[30]
    for d in (-4.0, 4.0):
        view = street.render(shift_left(street, 30, c2w, d), street.cameras["front"].K(), W, H)
        assert view["sky"][0, :H // 4].any()
        assert not view["sky"][0, -H // 4:].any()


def test_bad_options_say_what_to_use():
    with pytest.raises(ValueError, match="front_left"):
        SyntheticStreet(cameras=("rear",))
    with pytest.raises(ValueError, match="curvature"):
        SyntheticStreet(curvature=0.05)


def test_culled_cast_equals_testing_every_ray_against_every_object():
    from paradrive.synthetic import raycast as rc

    street = SyntheticStreet(seed=5, frames=30, width=128, height=80, curvature=0.003)
    K = street.cameras["front"].K()
    c2w = street.c2w("front")
    poses = [c2w[0], shift_left(street, 12, c2w[12], -4.0), shift_left(street, 29, c2w[29], 4.0)]
    # a camera right beside a parked car: its hull crosses the near plane
    car = np.flatnonzero(street.layout.box_mat == street_mod.CAR)[5]
    s0, s1, l0, l1, _, _ = street.layout.boxes[car]
    x, y = street.arc.to_world(0.5 * (s0 + s1), l1 + 0.3 if l1 < 0 else l0 - 0.3)
    beside = c2w[0].copy()
    beside[:2, 3] = [float(x), float(y)]
    poses.append(beside)
    for pose in poses:
        fast, _, _ = rc.cast_camera(street.prims, pose, K, 128, 80, cull=True)
        slow, _, _ = rc.cast_camera(street.prims, pose, K, 128, 80, cull=False)
        np.testing.assert_array_equal(fast.t, slow.t)
        np.testing.assert_array_equal(fast.kind, slow.kind)
        np.testing.assert_array_equal(fast.index, slow.index)
        np.testing.assert_array_equal(fast.face, slow.face)
