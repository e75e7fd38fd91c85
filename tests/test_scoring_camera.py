"""Camera accuracy (RErr / TErr): generated frames located against their source video, whose
poses are known, and compared with the requested novel cameras in both forms.

The videos are the synthetic street's exact views at 320x192 (every 2nd of 24 frames, 12 a
video): the recording, and the true views 1-4 m to the side standing in for a perfect model."""

from __future__ import annotations

import numpy as np
import pytest

from paradrive import geometry
from paradrive.scoring import camera as C

OFFSETS = (1.0, 2.0, 3.0, 4.0, -2.0)
FRAMES = list(range(0, 24, 2))
SETTINGS = C.CameraSettings(stride=1)   # the test clips are short: every frame is scored


@pytest.fixture(scope="module")
def street_views():
    from paradrive.synthetic.street import SyntheticStreet

    street = SyntheticStreet(seed=7, frames=24, width=320, height=192, cameras=("front",))
    cam = street.cameras["front"]
    K = np.asarray(cam.K(), dtype=np.float64)
    recorded = street.c2w("front")[FRAMES]
    ego = street.ego2world()[FRAMES]

    def render(c2w):
        return street.render(c2w, K, cam.width, cam.height, frames=FRAMES)["rgb"]

    novel = {d: geometry.lateral_shift(recorded, ego, d) for d in OFFSETS}
    source = render(recorded)
    model = C.triangulate_source(source, recorded, K, SETTINGS)
    return {"K": K, "recorded": recorded, "source": source, "model": model, "novel": novel,
            "truth": {d: render(novel[d]) for d in OFFSETS}}


def test_the_source_model_holds_points_that_reproject_where_they_were_seen(street_views):
    model = street_views["model"]
    assert min(len(p) for p in model.xyz) >= 60     # every sampled frame has points to match
    for k in (0, 6, 11):
        uv, z = geometry.project(model.xyz[k], street_views["recorded"][k], street_views["K"])
        assert np.all(z > 0)
        assert np.median(np.linalg.norm(uv - model.xy[k], axis=1)) < 0.5


def test_the_true_shifted_view_is_located_near_the_requested_camera(street_views):
    # measured: 0.03 m at 1 m, 0.05-0.07 m at 2 m, 0.13 m at 3 m, 12 of 12 frames located each
    for d, bound in ((1.0, 0.1), (2.0, 0.2), (-2.0, 0.2), (3.0, 0.3)):
        found = C.locate(street_views["model"], street_views["truth"][d], street_views["K"], SETTINGS)
        errors = C.camera_errors(found, street_views["novel"][d])
        assert errors.located >= 9, (d, errors)
        assert errors.terr_m < bound, (d, errors)
        assert errors.rerr_m_deg < 0.5, (d, errors)


def test_the_recorded_video_scores_its_offset_in_the_metric_form(street_views):
    found = C.locate(street_views["model"], street_views["source"], street_views["K"], SETTINGS)
    assert found.located.all()
    terr = {d: C.camera_errors(found, street_views["novel"][d]).terr_m for d in OFFSETS}
    for d in OFFSETS:
        assert terr[d] == pytest.approx(abs(d), abs=0.05)
    assert terr[1.0] < terr[2.0] < terr[3.0] < terr[4.0]


def test_the_relative_form_cannot_see_a_lateral_shift(street_views):
    # the recorded path moves as every shifted one does: the paper's form scores it the same
    found = C.locate(street_views["model"], street_views["source"], street_views["K"], SETTINGS)
    relative = [C.camera_errors(found, street_views["novel"][d]) for d in OFFSETS]
    assert max(e.terr for e in relative) - min(e.terr for e in relative) < 0.02
    assert max(e.rerr_deg for e in relative) - min(e.rerr_deg for e in relative) < 0.1


def test_a_frame_without_features_is_not_located_and_gets_no_number(street_views):
    blank = np.full_like(street_views["source"], 128)
    errors = C.camera_errors(C.locate(street_views["model"], blank, street_views["K"], SETTINGS),
                             street_views["novel"][1.0])
    assert errors.sampled == len(FRAMES) and errors.located == 0
    assert errors.terr_m is errors.rerr_deg is errors.terr is errors.rerr_m_deg is None


def _path(n: int, yaw_deg: float = 0.0) -> np.ndarray:
    """A camera driving forward 1 m a frame, turning ``yaw_deg`` a frame about its y axis."""
    return np.stack([geometry.make_pose(geometry.rotation_about("y", np.radians(yaw_deg * i))[:3, :3],
                                        [0.0, 0.0, float(i)]) for i in range(n)])


def test_relative_errors_sum_the_rotation_angles_and_ignore_the_scale():
    ref = _path(5)
    assert C.relative_errors(ref, ref) == pytest.approx((0.0, 0.0), abs=1e-9)
    scaled = ref.copy()
    scaled[:, :3, 3] *= 3.0                                  # another scale: the same motion
    assert C.relative_errors(scaled, ref)[1] == pytest.approx(0.0, abs=1e-9)
    turning = _path(5, yaw_deg=1.0)                          # frame i is i degrees off
    assert C.relative_errors(turning, ref)[0] == pytest.approx(0 + 1 + 2 + 3 + 4, abs=1e-6)


def test_metric_errors_are_metres_and_degrees_per_frame():
    ref = _path(3)
    est = ref.copy()
    est[:, :3, 3] += [0.0, 0.0, 0.5]
    dist, angle = C.metric_errors(est, ref)
    np.testing.assert_allclose(dist, 0.5)
    np.testing.assert_allclose(angle, 0.0, atol=1e-6)


def test_the_source_model_survives_its_cache_arrays(street_views):
    model = street_views["model"]
    back = C.SourceModel.from_arrays(model.arrays())
    assert back.points == model.points
    for a, b in zip(model.xyz, back.xyz):
        np.testing.assert_array_equal(a, b)
    assert back.desc[3].dtype == np.uint8
