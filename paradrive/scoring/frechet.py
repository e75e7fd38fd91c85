"""The Fréchet distance between two Gaussians fitted to feature sets (FID, Heusel et al. 2017;
FVD, Unterthiner et al. 2018), in numpy without scipy.

    d² = |μ₁ − μ₂|² + Tr(Σ₁) + Tr(Σ₂) − 2 Tr((Σ₁ Σ₂)^½)

Tr((Σ₁ Σ₂)^½) is the sum of the square roots of the eigenvalues of Σ₁ Σ₂. With A and B the
centred features over √(N − 1) (Σ₁ = AᵀA, Σ₂ = BᵀB), those eigenvalues are the squared
singular values of A Bᵀ (N₁ x N₂), so with fewer samples than dimensions (FVD's 400-d logits of
tens of videos; FID of a few hundred frames against 2048-d features) the trace is the sum of
the singular values of that small matrix, exact for the singular covariances such sets have.
Otherwise (and from moments alone) Σ₁ = L Lᵀ by Cholesky and the eigenvalues are those of the
symmetric positive semi-definite Lᵀ Σ₂ L (a symmetric square root by ``eigh`` when Σ₁ is
singular). Round-off negatives are clipped to 0; no complex arithmetic and no ε added to the
diagonals, where scipy's ``sqrtm`` of the non-symmetric product needs pytorch-fid's ε retry.
"""

from __future__ import annotations

import numpy as np

__all__ = ["gaussian", "frechet_distance", "frechet_from_moments"]


def _checked(features: np.ndarray) -> np.ndarray:
    x = np.asarray(features, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"a Fréchet distance needs at least 2 samples of (N, D) features, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("features hold NaN or infinite values")
    return x


def gaussian(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """features: (N, D), one sample a row, N >= 2 -> (mean (D,), covariance (D, D)) in float64;
    the covariance is the unbiased one (N − 1), as pytorch-fid's ``np.cov(rowvar=False)``."""
    x = _checked(features)
    mu = x.mean(axis=0)
    centred = x - mu
    return mu, centred.T @ centred / (x.shape[0] - 1)


def _trace_sqrt_of_product(s1: np.ndarray, s2: np.ndarray) -> float:
    """Tr((s1 s2)^½) for symmetric PSD (D, D) s1, s2."""
    s1, s2 = (s1 + s1.T) / 2, (s2 + s2.T) / 2
    try:
        root = np.linalg.cholesky(s1)
    except np.linalg.LinAlgError:       # singular: the symmetric square root instead
        w, v = np.linalg.eigh(s1)
        root = v * np.sqrt(np.clip(w, 0.0, None))
    inner = root.T @ s2 @ root
    eig = np.linalg.eigvalsh((inner + inner.T) / 2)
    return float(np.sqrt(np.clip(eig, 0.0, None)).sum())


def frechet_from_moments(mu1: np.ndarray, sigma1: np.ndarray, mu2: np.ndarray, sigma2: np.ndarray) -> float:
    """d² between N(mu1, sigma1) and N(mu2, sigma2): mu (D,), sigma (D, D) symmetric PSD; >= 0."""
    mu1, mu2 = np.asarray(mu1, dtype=np.float64), np.asarray(mu2, dtype=np.float64)
    s1, s2 = np.asarray(sigma1, dtype=np.float64), np.asarray(sigma2, dtype=np.float64)
    if mu1.shape != mu2.shape or s1.shape != s2.shape or s1.shape != (mu1.size, mu1.size):
        raise ValueError(f"moments of different dimensions: mu {mu1.shape}/{mu2.shape}, sigma {s1.shape}/{s2.shape}")
    diff = mu1 - mu2
    d2 = float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * _trace_sqrt_of_product(s1, s2))
    return max(d2, 0.0)


def frechet_distance(features1: np.ndarray, features2: np.ndarray) -> float:
    """The Fréchet distance of the Gaussians fitted to features1 (N1, D) and features2 (N2, D)."""
    x1, x2 = _checked(features1), _checked(features2)
    if x1.shape[1] != x2.shape[1]:
        raise ValueError(f"features of different dimensions: {x1.shape} and {x2.shape}")
    if 2 * min(len(x1), len(x2)) > x1.shape[1]:
        return frechet_from_moments(*gaussian(x1), *gaussian(x2))
    mu1, mu2 = x1.mean(axis=0), x2.mean(axis=0)
    a = (x1 - mu1) / np.sqrt(len(x1) - 1)
    b = (x2 - mu2) / np.sqrt(len(x2) - 1)
    trace_sqrt = float(np.linalg.svd(a @ b.T, compute_uv=False).sum())
    diff = mu1 - mu2
    d2 = float(diff @ diff + np.sum(a * a) + np.sum(b * b) - 2.0 * trace_sqrt)
    return max(d2, 0.0)
