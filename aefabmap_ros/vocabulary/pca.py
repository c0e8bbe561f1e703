"""PCA fitted on training descriptors, with a [0, 1] scaling for the autoencoder.

``transform`` projects descriptors onto the first ``dim`` principal axes (centred), or, fitted by
``fit_match_projection``, onto the ``dim`` axes along which descriptors of different scene points
differ most relative to how one point's descriptors differ between neighbouring frames (both are
a linear projection, stored alike).
``scale`` maps projections into [0, 1] using a robust range fitted on the training
projections (the ``clip_percentile`` and ``100 - clip_percentile`` percentiles), and
clips there: the autoencoder's binary cross-entropy needs inputs in [0, 1].

Two ways to scale (``per_component``):
- False (default): one range for all components. Keeps the PCA geometry (a uniform
  scale + shift), so Euclidean distances, and therefore clusters, are those of the PCA
  space; low-variance components stay near the middle.
- True: one range per component. Equalises the components (like whitening), which
  amplifies the low-variance, noisier ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from aefabmap_ros.errors import ConfigError, DataError


@dataclass(frozen=True)
class PCA:
    mean: np.ndarray  # (D,) float32, training mean
    components: np.ndarray  # (P, D) float32, by decreasing variance (ratio): orthonormal rows for PCA
    explained_variance: np.ndarray  # (P,) float32 (for a match projection: variance over match variance)
    scale_lo: np.ndarray  # (P,) float32, projection value mapped to 0
    scale_hi: np.ndarray  # (P,) float32, projection value mapped to 1 (> scale_lo)

    @property
    def input_dim(self) -> int:
        return int(self.components.shape[1])

    @property
    def dim(self) -> int:
        return int(self.components.shape[0])

    def transform(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) -> (N, P) float32 projections."""
        x = self._check(descriptors)
        result: np.ndarray = ((x - self.mean) @ self.components.T).astype(np.float32, copy=False)
        return result

    def scale(self, projections: np.ndarray) -> np.ndarray:
        """(N, P) projections -> (N, P) float32 in [0, 1] (clipped outside the training range)."""
        scaled = (projections - self.scale_lo) / (self.scale_hi - self.scale_lo)
        result: np.ndarray = np.clip(scaled, 0.0, 1.0).astype(np.float32, copy=False)
        return result

    def transform_scaled(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, D) descriptors -> (N, P) float32 in [0, 1]: the autoencoder's input."""
        return self.scale(self.transform(descriptors))

    def _check(self, descriptors: np.ndarray) -> np.ndarray:
        if descriptors.ndim != 2 or descriptors.shape[1] != self.input_dim:
            raise DataError(
                f"PCA expects (N, {self.input_dim}) descriptors, got shape {descriptors.shape}"
            )
        return np.asarray(descriptors, dtype=np.float32)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {
            "mean": self.mean,
            "components": self.components,
            "explained_variance": self.explained_variance,
            "scale_lo": self.scale_lo,
            "scale_hi": self.scale_hi,
        }

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> PCA:
        """Rebuild from ``to_arrays`` output, checking shapes (DataError naming the array)."""
        missing = [k for k in ("mean", "components", "explained_variance", "scale_lo", "scale_hi")
                   if k not in arrays]
        if missing:
            raise DataError(f"PCA arrays missing: {missing}")
        pca = cls(**{k: np.asarray(arrays[k], np.float32) for k in
                     ("mean", "components", "explained_variance", "scale_lo", "scale_hi")})
        p, d = pca.components.shape if pca.components.ndim == 2 else (-1, -1)
        checks = {
            "components": pca.components.ndim == 2 and p > 0 and d > 0,
            "mean": pca.mean.shape == (d,),
            "explained_variance": pca.explained_variance.shape == (p,),
            "scale_lo": pca.scale_lo.shape == (p,),
            "scale_hi": pca.scale_hi.shape == (p,) and bool(np.all(pca.scale_hi > pca.scale_lo)),
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise DataError(
                f"PCA arrays inconsistent: {bad} (components {pca.components.shape}, mean {pca.mean.shape})"
            )
        if not all(np.all(np.isfinite(v)) for v in pca.to_arrays().values()):
            raise DataError("PCA arrays contain NaN or infinity")
        return pca


def fit_pca(
    descriptors: np.ndarray,
    dim: int,
    per_component: bool = False,
    clip_percentile: float = 0.5,
) -> PCA:
    """Fit PCA on (N, D) training descriptors, keeping ``dim`` components (``dim`` <= D and < N)."""
    if descriptors.ndim != 2 or descriptors.shape[0] < 2:
        raise DataError(f"fit_pca needs (N >= 2, D) descriptors, got shape {descriptors.shape}")
    d = descriptors.shape[1]
    if not 1 <= dim <= d:
        raise ConfigError(f"pca_dim={dim} must be in [1, {d}] for {d}-d descriptors")
    if not 0.0 <= clip_percentile < 50.0:
        raise ConfigError(f"clip_percentile={clip_percentile} must be in [0, 50)")
    x = np.asarray(descriptors, np.float64)
    if not np.all(np.isfinite(x)):
        raise DataError("fit_pca: descriptors contain NaN or infinity")
    mean = x.mean(axis=0)
    covariance = np.cov(x - mean, rowvar=False, bias=True)
    eigenvalues, eigenvectors = np.linalg.eigh(covariance)
    order = np.argsort(eigenvalues)[::-1][:dim]
    components = eigenvectors[:, order].T
    # Sign convention (largest |loading| positive) so that a refit on the same data is identical.
    signs = np.sign(components[np.arange(dim), np.argmax(np.abs(components), axis=1)])
    components *= np.where(signs == 0, 1.0, signs)[:, None]
    projections = (x - mean) @ components.T
    lo, hi = _scale_range(projections, per_component, clip_percentile)
    return PCA(
        mean=mean.astype(np.float32),
        components=components.astype(np.float32),
        explained_variance=np.maximum(eigenvalues[order], 0.0).astype(np.float32),
        scale_lo=lo.astype(np.float32),
        scale_hi=hi.astype(np.float32),
    )


def fit_match_projection(
    descriptors: np.ndarray,
    pairs: np.ndarray,
    dim: int,
    per_component: bool = False,
    clip_percentile: float = 0.5,
    ridge: float = 1e-3,
) -> PCA:
    """The ``dim`` discriminant axes of (N, D) descriptors given (M, 2) row pairs of one scene point.

    Linear discriminant analysis with each scene point a class: the generalised eigenvectors of
    ``S_all w = l S_match w``, S_all the descriptors' covariance and S_match half the covariance of
    the pairs' differences (the spread of one point's descriptor from frame to frame), largest l
    first. Scaled so that ``w' S_match w = 1``: squared distances in the projection are in units of
    that frame-to-frame spread, the same for every axis, which is what nearest-centre words need to
    keep the two views of a point in one word. ``ridge`` (times the mean match variance) keeps
    S_match invertible along directions the pairs never vary in.
    """
    if descriptors.ndim != 2 or descriptors.shape[0] < 2:
        raise DataError(f"fit_match_projection needs (N >= 2, D) descriptors, got shape {descriptors.shape}")
    d = descriptors.shape[1]
    if not 1 <= dim <= d:
        raise ConfigError(f"pca_dim={dim} must be in [1, {d}] for {d}-d descriptors")
    if pairs.ndim != 2 or pairs.shape[1] != 2 or len(pairs) < 2 or pairs.min() < 0 or pairs.max() >= len(descriptors):
        raise DataError(f"the match projection needs (M >= 2, 2) row pairs into {len(descriptors)} descriptors, "
                        f"got shape {pairs.shape}")
    x = np.asarray(descriptors, np.float64)
    if not np.all(np.isfinite(x)):
        raise DataError("fit_match_projection: descriptors contain NaN or infinity")
    mean = x.mean(axis=0)
    covariance = np.cov(x - mean, rowvar=False, bias=True)
    differences = x[pairs[:, 0]] - x[pairs[:, 1]]
    match_covariance = differences.T @ differences / (2.0 * len(differences))
    match_covariance += ridge * np.trace(match_covariance) / d * np.eye(d)
    ratios, vectors = scipy.linalg.eigh(covariance, match_covariance)
    order = np.argsort(ratios)[::-1][:dim]
    components = vectors[:, order].T
    signs = np.sign(components[np.arange(dim), np.argmax(np.abs(components), axis=1)])
    components *= np.where(signs == 0, 1.0, signs)[:, None]
    lo, hi = _scale_range((x - mean) @ components.T, per_component, clip_percentile)
    return PCA(mean=mean.astype(np.float32), components=components.astype(np.float32),
               explained_variance=ratios[order].astype(np.float32), scale_lo=lo.astype(np.float32),
               scale_hi=hi.astype(np.float32))


def _scale_range(projections: np.ndarray, per_component: bool, clip_percentile: float) -> tuple[
        np.ndarray, np.ndarray]:
    dim = projections.shape[1]
    if per_component:
        lo = np.percentile(projections, clip_percentile, axis=0)
        hi = np.percentile(projections, 100.0 - clip_percentile, axis=0)
    else:
        lo = np.full(dim, np.percentile(projections, clip_percentile))
        hi = np.full(dim, np.percentile(projections, 100.0 - clip_percentile))
    # A degenerate (constant) component still needs a non-empty range.
    hi = np.where(hi > lo, hi, lo + 1.0)
    return lo, hi
