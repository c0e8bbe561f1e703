"""Tests for PCA + [0, 1] scaling (aefabmap_ros/vocabulary/pca.py)."""

import numpy as np
import pytest

from aefabmap_ros.errors import ConfigError, DataError
from aefabmap_ros.vocabulary.pca import PCA, fit_match_projection, fit_pca


def _data(n: int = 2000, d: int = 16, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    scales = np.linspace(10, 0.1, d)
    rotation, _ = np.linalg.qr(rng.normal(size=(d, d)))
    return (rng.normal(size=(n, d)) * scales) @ rotation.T + 5.0


def test_pca_matches_svd_reference() -> None:
    x = _data()
    pca = fit_pca(x, 4)
    centred = x - x.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    for k in range(4):  # same axes up to sign
        assert abs(abs(float(pca.components[k] @ vt[k])) - 1.0) < 1e-4
    np.testing.assert_allclose(pca.explained_variance, s[:4] ** 2 / len(x), rtol=1e-4)
    proj = pca.transform(x)
    assert proj.shape == (2000, 4) and proj.dtype == np.float32
    np.testing.assert_allclose(np.abs(proj), np.abs(centred @ vt[:4].T), rtol=1e-3, atol=1e-3)


@pytest.mark.parametrize("per_component", [False, True])
def test_scaling_is_in_unit_range_and_clipped(per_component: bool) -> None:
    x = _data()
    pca = fit_pca(x, 8, per_component=per_component, clip_percentile=1.0)
    scaled = pca.transform_scaled(x)
    assert scaled.min() >= 0.0 and scaled.max() <= 1.0
    # about 1 % of values clip at each end, the rest spread over the range
    assert 0.005 < float(np.mean(scaled == 0.0)) < 0.02
    far = pca.transform_scaled(np.full((1, 16), 1e6))
    assert np.all((far == 0.0) | (far == 1.0))
    if not per_component:  # one range: a uniform affine map keeps distances' ratios
        lo, hi = pca.scale_lo[0], pca.scale_hi[0]
        assert np.all(pca.scale_lo == lo) and np.all(pca.scale_hi == hi)


def test_round_trip_and_validation() -> None:
    pca = fit_pca(_data(), 4)
    again = PCA.from_arrays(pca.to_arrays())
    np.testing.assert_array_equal(again.components, pca.components)
    arrays = pca.to_arrays()
    arrays["mean"] = arrays["mean"][:5]
    with pytest.raises(DataError, match=r"inconsistent: \['mean'\]"):
        PCA.from_arrays(arrays)
    with pytest.raises(DataError, match="missing"):
        PCA.from_arrays({"mean": pca.mean})
    bad = pca.to_arrays()
    bad["components"] = np.full_like(bad["components"], np.nan)
    with pytest.raises(DataError, match="NaN"):
        PCA.from_arrays(bad)


def test_errors_name_the_problem() -> None:
    with pytest.raises(ConfigError, match=r"pca_dim=20 must be in \[1, 16\]"):
        fit_pca(_data(), 20)
    with pytest.raises(DataError, match="N >= 2"):
        fit_pca(np.zeros((1, 4)), 2)
    with pytest.raises(DataError, match="NaN"):
        fit_pca(np.full((5, 4), np.nan), 2)
    with pytest.raises(ConfigError, match="clip_percentile"):
        fit_pca(_data(), 2, clip_percentile=60)
    with pytest.raises(DataError, match=r"expects \(N, 16\)"):
        fit_pca(_data(), 2).transform(np.zeros((3, 8)))


def test_constant_component_still_gets_a_range() -> None:
    x = _data()
    x[:, :] = x[:, :1]  # rank one: later components are constant
    pca = fit_pca(x, 3, per_component=True)
    assert np.all(pca.scale_hi > pca.scale_lo)
    assert np.all(np.isfinite(pca.transform_scaled(x)))


def _two_views(points: int = 4000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Scene points seen twice: axes 0-1 vary widely between points but as widely between the two views of a
    point (std 10 each); axes 2-3 vary less between points (std 3) and hardly between views (std 0.1)."""
    rng = np.random.default_rng(seed)
    scene = rng.normal(size=(points, 4)) * np.array([10.0, 10.0, 3.0, 3.0])
    view_noise = np.array([10.0, 10.0, 0.1, 0.1])
    views = [scene + rng.normal(size=scene.shape) * view_noise for _ in range(2)]
    pairs = np.stack([np.arange(points), np.arange(points) + points], axis=1)
    return np.concatenate(views).astype(np.float32), pairs


def test_match_projection_keeps_the_axes_views_agree_on() -> None:
    x, pairs = _two_views()
    projection = fit_match_projection(x, pairs, 2, ridge=0.0)
    # Closed form for these diagonal covariances: the discriminant axes are e2 and e3, with ratio
    # (point variance + view variance) / view variance = (9 + 0.01) / 0.01 = 901, scaled to w' S_match w = 1,
    # i.e. |w| = 1 / 0.1.
    assert np.all(np.abs(projection.components[:, :2]) < 0.05 * np.abs(projection.components[:, 2:]).max())
    np.testing.assert_allclose(np.linalg.norm(projection.components, axis=1), 10.0, rtol=0.05)
    np.testing.assert_allclose(projection.explained_variance, 901.0, rtol=0.1)
    differences = projection.transform(x[pairs[:, 0]]) - projection.transform(x[pairs[:, 1]])
    np.testing.assert_allclose(differences.var(axis=0) / 2.0, 1.0, rtol=0.1)
    # The default ridge adds 1e-3 of the mean match variance ((100 + 100 + 0.01 + 0.01) / 4) to every axis's.
    ridged = fit_match_projection(x, pairs, 2)
    np.testing.assert_allclose(np.linalg.norm(ridged.components, axis=1), 1.0 / np.sqrt(0.01 + 0.05), rtol=0.05)
    # PCA of the same rows keeps the widest axes instead, the ones the two views disagree on.
    assert np.all(np.abs(fit_pca(x, 2).components[:, 2:]) < 0.05)


def test_match_projection_refuses_bad_pairs() -> None:
    x, pairs = _two_views(50)
    with pytest.raises(DataError, match="row pairs"):
        fit_match_projection(x, pairs[:, :1], 2)
    with pytest.raises(DataError, match="row pairs"):
        fit_match_projection(x, pairs + 100, 2)
    with pytest.raises(ConfigError, match="pca_dim=5"):
        fit_match_projection(x, pairs, 5)
