"""PCA fitted on training descriptors, with a [0, 1] scaling for the autoencoder.

``transform`` projects descriptors onto the first ``dim`` principal axes (centred).
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

from aefabmap_ros.errors import ConfigError, DataError


@dataclass(frozen=True)
class PCA:
    mean: np.ndarray  # (D,) float32, training mean
    components: np.ndarray  # (P, D) float32, orthonormal rows, by decreasing variance
    explained_variance: np.ndarray  # (P,) float32
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
