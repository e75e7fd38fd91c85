"""The SfM library: pycolmap on a real image sequence (deterministic, intrinsics held), the road
plane and the metric rig against known geometry."""

from __future__ import annotations

import contextlib
import os
import sqlite3

import numpy as np
import pytest

from paradrive import geometry
from paradrive.ingest import sfm
from paradrive.ingest.roadmotion import road_motion_height
from paradrive.scene import write_image
from paradrive.synthetic import SyntheticStreet


def test_registered_runs_and_their_text():
    reg = np.array([1, 1, 0, 1, 1, 1, 0, 0, 1], dtype=bool)
    assert sfm.registered_runs(reg) == [(0, 1), (3, 5), (8, 8)]
    assert sfm.format_runs(sfm.registered_runs(reg)) == "0-1, 3-5, 8"
    assert sfm.format_runs([]) == "none"


def similarity(seed: int) -> tuple[np.ndarray, float]:
    """A random rotation and translation, and a scale: a reconstruction's arbitrary frame."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)
    return geometry.make_pose(geometry.quaternion_to_rotation(q / np.linalg.norm(q)),
                              rng.normal(size=3) * 5), 0.137


def model_of(c2w_world: np.ndarray, points_world: np.ndarray, seed: int = 0) -> sfm.Reconstruction:
    """The world trajectory and points as a reconstruction would hold them (scaled, moved)."""
    move, s = similarity(seed)
    c2w = c2w_world.copy()
    c2w[:, :3, 3] *= s
    c2w = np.einsum("ij,fjk->fik", move, c2w)
    pts = (points_world * s) @ move[:3, :3].T + move[:3, 3]
    # each point's first frame: the last camera behind it (it is seen ahead)
    first = np.searchsorted(c2w_world[:, 0, 3], points_world[:, 0] - 4.0).clip(0, len(c2w) - 1)
    return sfm.Reconstruction(c2w=c2w, points=pts, colors=np.zeros_like(pts, dtype=np.uint8),
                              point_frame=first, point_views=np.full(len(pts), 5),
                              intrinsics=sfm.Intrinsics(100, 100, 80, 48),
                              distortion=(0.0,) * 5, estimated=False, seconds=0.0)


def street_points(rng: np.random.Generator) -> np.ndarray:
    """Road markings (z = 0, noisy), a raised sidewalk and facades, along 40 m."""
    road = np.c_[rng.uniform(0, 40, 400), rng.uniform(-5, 5, 400), rng.normal(0, 0.03, 400)]
    walk = np.c_[rng.uniform(0, 40, 150), rng.choice([-7.0, 7.0], 150), np.full(150, 0.15)]
    facade = np.c_[rng.uniform(0, 40, 400), rng.choice([-9.0, 9.0], 400), rng.uniform(0, 8, 400)]
    return np.concatenate([road, walk, facade])


def test_road_plane_gives_up_and_metric_scale():
    street = SyntheticStreet(name="demo", seed=7, frames=30, width=160, height=96)
    truth = street.c2w("front")
    rec = model_of(truth, street_points(np.random.default_rng(1)))
    plane = sfm.fit_road_plane(rec)
    move, s = similarity(0)
    np.testing.assert_allclose(plane.normal, move[:3, 2], atol=0.02)
    assert plane.height / s == pytest.approx(1.6, rel=0.03)
    rig = sfm.metric_rig(rec.c2w, plane.normal, plane.height, 1.6 / plane.height)
    np.testing.assert_allclose(rig.ego2world[0], np.eye(4), atol=1e-9)
    np.testing.assert_allclose(rig.ego2world @ rig.cam2ego, rig.c2w, atol=1e-9)
    # the truth's world is its first ego pose too, 1.5 m behind the camera: only that differs,
    # besides the height's noise (a few tenths of a per cent of scale over the 23 m path)
    back = geometry.translation(1.5, 0, 0)
    np.testing.assert_allclose((back @ rig.c2w)[:, :3, 3], truth[:, :3, 3], atol=0.15)
    np.testing.assert_allclose(rig.points(rec.points[:3]), street_points(np.random.default_rng(1))[:3]
                               - [1.5, 0, 0], atol=0.15)


def layered_street(rng: np.random.Generator) -> np.ndarray:
    """Sparse road markings (z = 0) under three times as many points 0.12 m up beside the lane
    (kerbs, sidewalk, parked car bodies), a denser vehicle 0.6 m up ahead in the lane, and
    mismatched points scattered below the road, each with 3 cm of triangulation noise."""
    road = np.c_[rng.uniform(0, 40, 150), rng.choice([-1.75, 1.75], 150), np.zeros(150)]
    beside = np.c_[rng.uniform(0, 40, 450), rng.choice([-1, 1], 450) * rng.uniform(2.6, 6, 450),
                   np.full(450, 0.12)]
    vehicle = np.c_[rng.uniform(10, 14, 200), rng.uniform(-0.9, 0.9, 200), np.full(200, 0.6)]
    below = np.c_[rng.uniform(0, 40, 30), rng.uniform(-2, 2, 30), rng.uniform(-0.8, -0.2, 30)]
    points = np.concatenate([road, beside, vehicle, below])
    return points + rng.normal(0, 0.03, points.shape)


def test_the_road_is_the_lowest_dense_layer_in_the_ego_lane():
    street = SyntheticStreet(name="demo", seed=7, frames=30, width=160, height=96)
    rec = model_of(street.c2w("front"), layered_street(np.random.default_rng(3)))
    plane = sfm.fit_road_plane(rec)
    _, s = similarity(0)
    assert plane.height / s == pytest.approx(1.6, rel=0.01)
    assert plane.inliers < 150  # the road markings only, none of the layers above or below


def test_a_bank_or_a_row_of_roofs_holding_more_points_is_not_the_road():
    """Sparse lane markings beside (a) an embankment rising 15 degrees sideways, a plane within
    the tilt a dashcam's pitch allows that holds twice the road's points, and (b) a level row of
    car roofs 1.2 m up, beside the lane, denser than the road: the road is still found."""
    street = SyntheticStreet(name="demo", seed=7, frames=30, width=160, height=96)
    rng = np.random.default_rng(5)
    road = np.c_[rng.uniform(0, 40, 150), rng.choice([-1.75, 1.75], 150), np.zeros(150)]
    y = rng.uniform(2.5, 12, 300)
    bank = np.c_[rng.uniform(0, 40, 300), y, (y - 2.0) * np.tan(np.deg2rad(15))]
    roofs = np.c_[rng.uniform(0, 40, 400), rng.choice([-1, 1], 400) * rng.uniform(3, 5, 400),
                  np.full(400, 1.2)]
    _, s = similarity(0)
    for beside in (bank, roofs):
        points = np.concatenate([road, beside])
        plane = sfm.fit_road_plane(model_of(street.c2w("front"), points + rng.normal(0, 0.02, points.shape)))
        assert plane.height / s == pytest.approx(1.6, rel=0.02)


def test_a_camera_that_sees_no_road_has_no_plane():
    street = SyntheticStreet(name="demo", seed=7, frames=10, width=160, height=96)
    rng = np.random.default_rng(2)
    sky_only = np.c_[rng.uniform(0, 40, 100), rng.uniform(-5, 5, 100), rng.uniform(3, 9, 100)]
    with pytest.raises(sfm.SfmError, match="road"):
        sfm.fit_road_plane(model_of(street.c2w("front"), sky_only))


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    street = SyntheticStreet(name="demo", seed=7, frames=16, width=320, height=192)
    spec = street.cameras["front"]
    rgb = street.render(street.c2w("front"), spec.K(), spec.width, spec.height)["rgb"]
    folder = tmp_path_factory.mktemp("frames")
    names = [f"{i:06d}.png" for i in range(len(rgb))]
    for name, pixels in zip(names, rgb):
        write_image(folder / name, pixels)
    return folder, names, street, spec


def database_rows(path) -> dict[str, list]:
    with contextlib.closing(sqlite3.connect(path)) as db:
        tables = [t for (t,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")]
        return {t: db.execute(f"SELECT * FROM {t} ORDER BY rowid").fetchall() for t in tables}


def test_features_take_the_threads_omp_num_threads_gives_else_every_cpu(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "3")   # as Ray sets it to a task's CPUs
    assert sfm.feature_threads() == 3
    monkeypatch.delenv("OMP_NUM_THREADS")
    assert sfm.feature_threads() == len(os.sched_getaffinity(0))


def test_reconstruct_registers_every_frame_the_same_way_on_one_thread_and_on_three(tmp_path, frames,
                                                                                   monkeypatch):
    """The features are found on several threads, which store the images in the order they
    finish: renumbered, the database and the poses are one thread's, byte for byte."""
    folder, names, street, spec = frames
    K = sfm.Intrinsics(spec.fx, spec.fy, spec.cx, spec.cy)
    monkeypatch.setattr(sfm, "feature_threads", lambda: 1)
    a = sfm.reconstruct(folder, names, tmp_path / "a", intrinsics=K)
    monkeypatch.setattr(sfm, "feature_threads", lambda: 3)
    b = sfm.reconstruct(folder, names, tmp_path / "b", intrinsics=K)
    assert a.registered.all() and a.models == 1 and not a.estimated
    assert a.intrinsics == K  # held fixed
    one, three = database_rows(tmp_path / "a" / "database.db"), database_rows(tmp_path / "b" / "database.db")
    assert one.keys() == three.keys() and len(one["images"]) == len(names)
    for table in one:
        assert one[table] == three[table], table
    np.testing.assert_array_equal(a.c2w, b.c2w)
    np.testing.assert_array_equal(a.points, b.points)
    truth = street.c2w("front")
    s = sfm.path_length(truth) / sfm.path_length(a.c2w)
    rel = np.einsum("fij,fjk->fik", np.linalg.inv(a.c2w[:1]), a.c2w)[:, :3, 3] * s
    true_rel = np.einsum("fij,fjk->fik", np.linalg.inv(truth[:1]), truth)[:, :3, 3]
    np.testing.assert_allclose(rel, true_rel, atol=0.02 * sfm.path_length(truth))


def test_the_road_s_motion_measures_the_camera_height(frames):
    """The true frames and poses in a model's frame and units, with a first guess 6 % off (as the
    SfM points give): the road's motion finds the height within 1.5 %, the same twice."""
    _, _, street, spec = frames
    rgb = street.render(street.c2w("front"), spec.K(), spec.width, spec.height)["rgb"]
    move, s = similarity(4)
    c2w = street.c2w("front").copy()
    c2w[:, :3, 3] *= s
    c2w = np.einsum("ij,fjk->fik", move, c2w)
    up = move[:3, 2]
    args = (lambda k: rgb[k], c2w, spec.K(), up, 1.06 * 1.6 * s)
    found = road_motion_height(*args)
    assert found is not None and len(found.pairs) >= 5
    assert found.height / s == pytest.approx(1.6, rel=0.015)
    assert road_motion_height(*args).height == found.height
    # a car's hood over the bottom 15 % of every frame, textured but moving with the camera
    hooded = rgb.copy()
    band = len(rgb[0]) * 15 // 100
    hooded[:, -band:] = np.random.default_rng(0).integers(80, 140, hooded[0, -band:].shape)
    under_hood = road_motion_height(lambda k: hooded[k], *args[1:])
    assert under_hood is not None and under_hood.height / s == pytest.approx(1.6, rel=0.02)
    # or given as the ego mask, made on frames twice the size: the same pixels are left out
    ego = np.zeros((2 * rgb.shape[1], 2 * rgb.shape[2]), dtype=bool)
    ego[-2 * band:] = True
    masked = road_motion_height(lambda k: hooded[k], *args[1:], ego=ego)
    assert masked is not None and masked.height / s == pytest.approx(1.6, rel=0.02)
    # a road with no texture cannot be measured: no pair aligns
    flat = np.full_like(rgb[0], 128)
    assert road_motion_height(lambda k: flat, *args[1:]) is None


def test_a_static_overlay_over_the_road_cancels_out():
    """A reflection in the windscreen (bright lines across the lane, the same in every frame)
    would hold the fit towards no motion; aligning each pair after the mean of the frames that
    show other road takes it away: the height is the one the clean frames give."""
    street = SyntheticStreet(name="demo", seed=7, frames=40, width=320, height=192)
    spec = street.cameras["front"]
    rgb = street.render(street.c2w("front"), spec.K(), spec.width, spec.height)["rgb"]
    move, s = similarity(4)
    c2w = street.c2w("front").copy()
    c2w[:, :3, 3] *= s
    c2w = np.einsum("ij,fjk->fik", move, c2w)
    reflected = rgb.astype(np.int16)
    for row, amplitude in ((140, 70), (152, 50), (165, 60)):
        reflected[:, row:row + 2, 40:280] += amplitude
    reflected = np.clip(reflected, 0, 255).astype(np.uint8)
    args = (c2w, spec.K(), move[:3, 2], 1.06 * 1.6 * s)
    clean = road_motion_height(lambda k: rgb[k], *args)
    found = road_motion_height(lambda k: reflected[k], *args)
    assert clean is not None and found is not None and len(found.pairs) >= 30
    assert found.height / s == pytest.approx(1.6, rel=0.02)
    assert found.height == pytest.approx(clean.height, rel=0.002)
    assert 0 < found.uncertainty < 0.05


def test_the_codec_part_is_how_far_one_more_encode_moves_the_height(frames):
    """The road's motion measured again on its frames after one more H.264 encode: the same
    figure every time (one encoder thread), the height itself untouched, its uncertainty
    holding the move; an encode that loses the road's alignment (CRF 28 at 320x192) counts as
    the whole height's worth. (One encode is one sample of what codecs do: at CRF 10 and 18
    it moved these frames 1.1 and 2.5 % over 40 pairs, 1.2 and 0.5 % over 12.)"""
    _, _, street, spec = frames
    rgb = street.render(street.c2w("front"), spec.K(), spec.width, spec.height)["rgb"]
    args = (lambda k: rgb[k], street.c2w("front"), spec.K(), np.array([0.0, 0.0, 1.0]), 1.6)
    plain = road_motion_height(*args, pairs=12)   # 12 of the 40 pairs: the same figures, sooner
    fine, again, coarse = (road_motion_height(*args, pairs=12, codec_crf=crf) for crf in (18, 18, 28))
    assert plain is not None and plain.codec is None and fine is not None and coarse is not None
    assert fine.height == plain.height and fine.codec == again.codec
    recoded = fine.recoded_heights[np.isfinite(fine.recoded_heights)]
    assert fine.codec == pytest.approx(abs(np.median(recoded) / plain.height - 1))
    assert fine.uncertainty == pytest.approx(np.sqrt(plain.uncertainty ** 2 + fine.codec ** 2))
    assert 0 < fine.codec < 0.1 and coarse.codec == 1.0
