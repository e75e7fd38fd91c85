"""The Fréchet distance (FID, FVD) and the metric values computed from features: checked against
scipy's ``sqrtm`` path (pytorch-fid's algorithm) and torchmetrics' eigenvalue path on the same
features, and against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from paradrive.scoring.features import clip_v, fid, fvd, iq
from paradrive.scoring.frechet import frechet_distance, frechet_from_moments, gaussian


def _scipy_frechet(a: np.ndarray, b: np.ndarray, eps: float = 1e-6) -> float:
    """pytorch-fid's computation: scipy's sqrtm of Σ₁Σ₂, an ε on the diagonals when not finite,
    the real part."""
    linalg = pytest.importorskip("scipy.linalg")
    mu1, s1 = a.mean(0), np.cov(a, rowvar=False)
    mu2, s2 = b.mean(0), np.cov(b, rowvar=False)
    covmean = linalg.sqrtm(s1 @ s2)
    if not np.isfinite(covmean).all():
        offset = np.eye(len(s1)) * eps
        covmean = linalg.sqrtm((s1 + offset) @ (s2 + offset))
    diff = mu1 - mu2
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean.real))


def _features(rng, n: int, d: int, scale: float = 1.0, shift: float = 0.0) -> np.ndarray:
    mix = rng.standard_normal((d, d)) / np.sqrt(d)
    return rng.standard_normal((n, d)) @ mix * scale + shift


# (samples, dimensions, relative tolerance): full-rank covariances agree to round-off; with fewer
# samples than dimensions (singular covariances, as FVD's 400-d logits of 60 videos per offset)
# sqrtm of the singular product is itself only accurate to ~1e-8
CASES = [(500, 16, 1e-10), (300, 64, 1e-9), (40, 64, 1e-6), (20, 256, 1e-6)]


@pytest.mark.parametrize("n,d,tol", CASES)
def test_frechet_matches_scipy_sqrtm(n, d, tol):
    rng = np.random.default_rng(n + d)
    a, b = _features(rng, n, d), _features(rng, n, d, scale=1.3, shift=0.2)
    ours, ref = frechet_distance(a, b), _scipy_frechet(a, b)
    assert ref > 1.0
    assert ours == pytest.approx(ref, rel=tol)


@pytest.mark.parametrize("n,d,tol", CASES)
def test_frechet_matches_torchmetrics(n, d, tol):
    torch = pytest.importorskip("torch")
    compute_fid = pytest.importorskip("torchmetrics.image.fid")._compute_fid
    rng = np.random.default_rng(7 * n + d)
    a, b = _features(rng, n, d), _features(rng, n, d, scale=0.8, shift=-0.1)
    moments = [torch.tensor(x, dtype=torch.float64, device="cpu") for x in (*gaussian(a), *gaussian(b))]
    assert frechet_distance(a, b) == pytest.approx(float(compute_fid(*moments)), rel=tol)


def test_the_few_sample_path_and_the_covariance_path_agree():
    rng = np.random.default_rng(11)
    a, b = _features(rng, 30, 200), _features(rng, 45, 200, scale=1.5, shift=0.3)   # 30 < 200: singular values
    assert frechet_distance(a, b) == pytest.approx(frechet_from_moments(*gaussian(a), *gaussian(b)), rel=1e-8)


def test_a_singular_covariance_with_many_samples_matches_scipy():
    rng = np.random.default_rng(12)
    a, b = _features(rng, 300, 64), _features(rng, 300, 64, scale=1.2)
    a[:, 10] = a[:, 3]          # rank 63: Cholesky fails, the symmetric root takes over
    assert frechet_distance(a, b) == pytest.approx(_scipy_frechet(a, b), rel=1e-8)


def test_identical_sets_are_at_distance_zero():
    a = _features(np.random.default_rng(1), 50, 128)       # singular covariance: 50 < 128
    assert frechet_distance(a, a) == pytest.approx(0.0, abs=1e-8 * np.trace(np.cov(a, rowvar=False)))


def test_a_shifted_set_is_at_the_squared_shift():
    rng = np.random.default_rng(2)
    a = _features(rng, 200, 32)
    delta = rng.standard_normal(32)
    assert frechet_distance(a, a + delta) == pytest.approx(float(delta @ delta), rel=1e-9)
    assert frechet_distance(a, a + 2 * delta) == pytest.approx(4 * float(delta @ delta), rel=1e-9)


def test_diagonal_gaussians_have_the_closed_form():
    rng = np.random.default_rng(3)
    v1, v2 = rng.uniform(0.1, 2, 20), rng.uniform(0.1, 2, 20)
    mu1, mu2 = rng.standard_normal(20), rng.standard_normal(20)
    expected = float(((mu1 - mu2) ** 2).sum() + ((np.sqrt(v1) - np.sqrt(v2)) ** 2).sum())
    assert frechet_from_moments(mu1, np.diag(v1), mu2, np.diag(v2)) == pytest.approx(expected, rel=1e-12)


def test_the_distance_grows_with_the_spread_of_the_difference():
    rng = np.random.default_rng(4)
    a = _features(rng, 300, 16)
    distances = [frechet_distance(a, _features(np.random.default_rng(5), 300, 16, scale=s)) for s in (1, 2, 4)]
    assert distances[0] < distances[1] < distances[2]


def test_fewer_than_two_samples_or_non_finite_features_are_refused():
    with pytest.raises(ValueError, match="at least 2 samples"):
        frechet_distance(np.zeros((1, 4)), np.zeros((5, 4)))
    bad = np.ones((5, 4))
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        frechet_distance(bad, np.ones((5, 4)))


def test_fid_pools_the_frames_of_all_videos_and_fvd_one_row_per_video():
    rng = np.random.default_rng(6)
    videos = [rng.standard_normal((t, 8)) for t in (5, 7, 3)]
    generated = [rng.standard_normal((6, 8)) + 0.5, rng.standard_normal((4, 8))]
    assert fid(videos, generated) == frechet_distance(np.vstack(videos), np.vstack(generated))
    per_video = [rng.standard_normal((1, 8)) for _ in range(12)]
    other = [rng.standard_normal((1, 8)) * 2 for _ in range(10)]
    assert fvd(per_video, other) == frechet_distance(np.vstack(per_video), np.vstack(other))


def test_clip_v_is_the_mean_cosine_of_matching_frames():
    rng = np.random.default_rng(7)
    a = rng.standard_normal((9, 16))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    assert clip_v(a, a) == pytest.approx(1.0, abs=1e-12)
    assert clip_v(a, -a) == pytest.approx(-1.0, abs=1e-12)
    b = rng.standard_normal((9, 16))
    expected = np.mean([x @ y / np.linalg.norm(y) for x, y in zip(a, b)])
    assert clip_v(a, b) == pytest.approx(expected, rel=1e-12)
    with pytest.raises(ValueError, match="same"):
        clip_v(a, a[:5])


def test_iq_is_the_mean_frame_score():
    assert iq(np.array([60.0, 70.0, 65.0])) == pytest.approx(65.0)
    with pytest.raises(ValueError):
        iq(np.zeros(0))
