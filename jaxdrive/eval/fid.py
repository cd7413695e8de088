"""The Fréchet distance between two Gaussians of features (FID, FVD) and their streamed statistics.

FID (Heusel et al. 2017, eq. 6; FVD, Unterthiner et al. 2018, uses the same distance on I3D
features) is ``||mu1 - mu2||^2 + Tr(S1 + S2 - 2 (S1 S2)^(1/2))``. :class:`FeatureStats` keeps the
running mean and scatter matrix of a feature stream in float64 (Chan et al.'s pairwise update, so
50k samples never sit in memory and a batch's order does not matter to numerical precision).
"""

from __future__ import annotations

import numpy as np


def frechet_distance(mu1, sigma1, mu2, sigma2) -> float:
    """``||mu1 - mu2||^2 + Tr(S1) + Tr(S2) - 2 Tr((S1 S2)^(1/2))`` in float64.

    ``Tr((S1 S2)^(1/2))`` is the sum of the square roots of the eigenvalues of the symmetric
    positive semi-definite ``S1^(1/2) S2 S1^(1/2)`` (similar to ``S1 S2``): no complex square
    root to clean up, and covariances of fewer samples than dimensions (rank deficient) are fine.
    """
    mu1, mu2 = np.atleast_1d(np.asarray(mu1, np.float64)), np.atleast_1d(np.asarray(mu2, np.float64))
    s1, s2 = np.atleast_2d(np.asarray(sigma1, np.float64)), np.atleast_2d(np.asarray(sigma2, np.float64))
    d = mu1.shape[0]
    for name, value, shape in (("mu2", mu2, (d,)), ("sigma1", s1, (d, d)), ("sigma2", s2, (d, d))):
        if value.shape != shape:
            raise ValueError(f"{name}: expected shape {list(shape)} (mu1 has {d} features), got {list(value.shape)}")
    for name, value in (("mu1", mu1), ("sigma1", s1), ("mu2", mu2), ("sigma2", s2)):
        if not np.isfinite(value).all():
            raise ValueError(f"{name}: expected finite values, got {int((~np.isfinite(value)).sum())} non-finite")
    w, v = np.linalg.eigh((s1 + s1.T) / 2)
    half = (v * np.sqrt(np.clip(w, 0, None))) @ v.T  # S1^(1/2)
    inner = np.linalg.eigvalsh(half @ ((s2 + s2.T) / 2) @ half)
    tr_covmean = np.sqrt(np.clip(inner, 0, None)).sum()
    diff = mu1 - mu2
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2 * tr_covmean)


class FeatureStats:
    """Running mean and covariance of ``[N, D]`` feature batches (float64).

    ``add(batch)`` folds a batch in; ``mean``, ``cov`` (unbiased, as ``np.cov``) and ``count``
    read them; ``fid(other)`` is the Fréchet distance to another stream's statistics."""

    def __init__(self, dim: int):
        if isinstance(dim, bool) or not isinstance(dim, (int, np.integer)) or dim < 1:
            raise ValueError(f"dim: expected a positive integer, got {dim!r}")
        self.dim = int(dim)
        self.count = 0
        self.mean = np.zeros(self.dim, np.float64)
        self._scatter = np.zeros((self.dim, self.dim), np.float64)

    def add(self, features) -> FeatureStats:
        x = np.asarray(features, np.float64)
        if x.ndim != 2 or x.shape[1] != self.dim:
            raise ValueError(f"features: expected [N, {self.dim}], got {list(x.shape)}")
        n = x.shape[0]
        if n == 0:
            return self
        mean_b = x.mean(0)
        centred = x - mean_b
        delta = mean_b - self.mean
        total = self.count + n
        self._scatter += centred.T @ centred + np.outer(delta, delta) * (self.count * n / total)
        self.mean = self.mean + delta * (n / total)
        self.count = total
        return self

    @property
    def cov(self) -> np.ndarray:
        if self.count < 2:
            raise ValueError(f"samples: expected at least 2 for a covariance, got {self.count}")
        return self._scatter / (self.count - 1)

    def fid(self, other: FeatureStats) -> float:
        return frechet_distance(self.mean, self.cov, other.mean, other.cov)
