"""Tests for feature extraction (aefabmap_ros/features/extraction.py)."""

import cv2
import numpy as np
import pytest

import aefabmap_ros.features.extraction as features_module
from aefabmap_ros.errors import ConfigError, DataError, ImageError
from aefabmap_ros.features.extraction import (
    FeatureConfig,
    check_descriptor_values,
    check_feature_config,
    descriptor_length,
    extract_features,
    rootsift,
    surf_available,
)


def _textured(seed: int = 0, shape: tuple[int, int] = (240, 320)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = np.zeros(shape, np.uint8)
    for _ in range(60):
        x, y = int(rng.integers(0, shape[1])), int(rng.integers(0, shape[0]))
        cv2.circle(image, (x, y), int(rng.integers(3, 20)), int(rng.integers(60, 255)), -1)
        cv2.rectangle(image, (x, y), (x + int(rng.integers(5, 30)), y + int(rng.integers(5, 30))),
                      int(rng.integers(0, 200)), 2)
    return cv2.GaussianBlur(image, (3, 3), 0)


@pytest.mark.parametrize(("kind", "dim", "dtype"), [("sift", 128, np.float32), ("rootsift", 128, np.float32),
                                                    ("orb", 32, np.uint8)])
def test_extract_shapes_types_and_limit(kind: str, dim: int, dtype: type) -> None:
    config = FeatureConfig(type=kind, max_features=50)
    features = extract_features(_textured(), config)
    n = len(features)
    assert 10 < n <= 50 + 5  # SIFT may keep ties at the cut
    assert features.keypoints.shape == (n, 5) and features.keypoints.dtype == np.float32
    assert features.descriptors.shape == (n, dim) and features.descriptors.dtype == dtype
    assert features.descriptor_type == kind
    assert np.all(np.isfinite(features.keypoints))
    assert descriptor_length(kind) == dim == descriptor_length(config)
    xy = features.keypoints[:, :2]
    assert np.all((xy >= 0) & (xy < [320, 240]))


def test_keypoints_match_opencv_directly() -> None:
    image = _textured(1)
    features = extract_features(image, FeatureConfig(max_features=0))
    sift = cv2.SIFT_create()  # type: ignore[attr-defined]
    cv_keypoints, cv_descriptors = sift.detectAndCompute(image, None)
    assert len(features) == len(cv_keypoints)
    np.testing.assert_allclose(features.keypoints[:, :2], [k.pt for k in cv_keypoints], atol=1e-4)
    np.testing.assert_allclose(features.descriptors, cv_descriptors)


def _blobs(seed: int = 0, shape: tuple[int, int] = (240, 320)) -> tuple[np.ndarray, np.ndarray]:
    """An image of Gaussian blobs at known sub-pixel centres (x, y), in OpenCV's convention (pixel
    centres at integer coordinates), and those centres."""
    rng = np.random.default_rng(seed)
    rows, columns = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    image = np.full(shape, 40.0)
    centres = []
    for y in range(30, shape[0] - 20, 45):
        for x in range(30, shape[1] - 20, 45):
            cx, cy, sigma = x + rng.uniform(-0.5, 0.5), y + rng.uniform(-0.5, 0.5), rng.uniform(3, 5)
            image += 180 * np.exp(-((columns - cx) ** 2 + (rows - cy) ** 2) / (2 * sigma**2))
            centres.append((cx, cy))
    return np.clip(image, 0, 255).round().astype(np.uint8), np.array(centres)


def _offsets_to_nearest(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    differences = points[:, None, :] - centres[None, :, :]
    nearest = np.linalg.norm(differences, axis=2).argmin(axis=1)
    return differences[np.arange(len(points)), nearest]


@pytest.mark.parametrize("kind", ["sift", "rootsift"])
def test_first_octave_zero_keypoints_are_in_image_pixels(kind: str) -> None:
    # The image is halved before OpenCV sees it; keypoints must come back on the blobs' true centres
    # (the verifier's geometry and depth lookup use them as pixels of the image it was given).
    image, centres = _blobs()
    features = extract_features(image, FeatureConfig(type=kind, sift_first_octave=0))
    offsets = _offsets_to_nearest(features.keypoints[:, :2], centres)
    on_blob = np.linalg.norm(offsets, axis=1) < 1.0
    assert on_blob.sum() >= 0.9 * len(centres)
    np.testing.assert_allclose(offsets[on_blob].mean(axis=0), 0.0, atol=0.05)  # no bias (x 2 + 0.5 would be 0.5)
    assert np.abs(offsets[on_blob]).max() < 0.3
    # the same blobs at the same scale as with OpenCV's doubling
    doubled = extract_features(image, FeatureConfig(type=kind, sift_first_octave=-1)).keypoints
    doubled_on_blob = np.linalg.norm(_offsets_to_nearest(doubled[:, :2], centres), axis=1) < 1.0
    assert np.median(features.keypoints[on_blob, 2]) == pytest.approx(np.median(doubled[doubled_on_blob, 2]), rel=0.1)


def test_first_octave_zero_finds_the_same_points_as_doubling() -> None:
    # Up to resampling it is the same scale space from its second octave on: keypoints matched between
    # the two settings land on the same image points (within a pixel) at the same sizes.
    image = _textured(3, (480, 640))
    doubled = extract_features(image, FeatureConfig(max_features=0, sift_double_below_pixels=0))
    octave_zero = extract_features(image, FeatureConfig(max_features=0, sift_first_octave=0))
    assert 0.2 * len(doubled) < len(octave_zero) < len(doubled)  # the doubled octave's fine keypoints are gone
    matches = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(octave_zero.descriptors, doubled.descriptors)
    pairs = np.array([(m.queryIdx, m.trainIdx) for m in matches if m.distance < 100])
    shift = octave_zero.keypoints[pairs[:, 0], :2] - doubled.keypoints[pairs[:, 1], :2]
    same_point = np.linalg.norm(shift, axis=1) < 1.0
    assert same_point.mean() > 0.9
    # OpenCV's doubling reports points a quarter pixel right and down of their true place (see extraction.py)
    np.testing.assert_allclose(np.median(shift[same_point], axis=0), -0.25, atol=0.1)
    size_ratio = octave_zero.keypoints[pairs[same_point, 0], 2] / doubled.keypoints[pairs[same_point, 1], 2]
    assert np.median(size_ratio) == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize("kind", ["sift", "rootsift"])
def test_only_images_under_640x480_are_doubled_by_default(kind: str) -> None:
    # 480 x 640 has exactly sift_double_below_pixels (307,200): it starts at octave 0, as an explicit
    # first octave 0 does; one row fewer is doubled, as OpenCV's SIFT does every image.
    vga = _textured(5, (480, 640))
    assert FeatureConfig().sift_double_below_pixels == 640 * 480
    expected_zero = extract_features(vga, FeatureConfig(type=kind, sift_first_octave=0))
    default = extract_features(vga, FeatureConfig(type=kind))
    np.testing.assert_array_equal(default.keypoints, expected_zero.keypoints)
    np.testing.assert_array_equal(default.descriptors, expected_zero.descriptors)
    smaller = vga[:479]
    always_doubled = extract_features(smaller, FeatureConfig(type=kind, sift_double_below_pixels=0))
    np.testing.assert_array_equal(extract_features(smaller, FeatureConfig(type=kind)).keypoints,
                                  always_doubled.keypoints)
    assert not np.array_equal(always_doubled.keypoints[:50], expected_zero.keypoints[:50])
    # the limit only widens what -1 doubles: first octave 0 never doubles, ORB ignores both
    assert FeatureConfig(sift_first_octave=0, sift_double_below_pixels=10**9).starts_at_octave_zero((10, 10))
    assert not FeatureConfig(type="orb").starts_at_octave_zero((4000, 4000))


@pytest.mark.parametrize("shape", [(241, 321), (1, 50), (3, 3)])
def test_first_octave_zero_takes_odd_and_tiny_images(shape: tuple[int, int]) -> None:
    image = _textured(4, shape) if min(shape) > 100 else np.full(shape, 100, np.uint8)
    features = extract_features(image, FeatureConfig(sift_first_octave=0))
    assert features.keypoints.shape[1] == 5 and features.descriptors.shape == (len(features), 128)
    assert np.all(features.keypoints[:, :2] < [shape[1], shape[0]])
    if min(shape) > 100:
        assert len(features) > 10


def test_rootsift_is_hellinger_normalised_sift() -> None:
    image = _textured(2)
    sift = extract_features(image, FeatureConfig(type="sift"))
    root = extract_features(image, FeatureConfig(type="rootsift"))
    expected = np.sqrt(sift.descriptors / sift.descriptors.sum(axis=1, keepdims=True))
    np.testing.assert_allclose(root.descriptors, expected, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(root.descriptors, axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(rootsift(np.zeros((1, 4), np.float32)), 0.0)


@pytest.mark.parametrize("kind", ["sift", "rootsift", "orb"])
def test_blank_image_yields_empty_arrays(kind: str) -> None:
    features = extract_features(np.full((100, 100), 128, np.uint8), FeatureConfig(type=kind))
    assert features.keypoints.shape == (0, 5)
    assert features.descriptors.shape == (0, descriptor_length(kind))
    assert features.descriptors.dtype == (np.uint8 if kind == "orb" else np.float32)


@pytest.mark.parametrize("bad", [np.zeros((10, 10, 3), np.uint8), np.zeros((10, 10), np.float32),
                                 np.zeros((0, 10), np.uint8), "image"])
def test_bad_images_are_refused(bad: object) -> None:
    with pytest.raises(ImageError, match=r"2-D uint8|empty image"):
        extract_features(bad, FeatureConfig())  # type: ignore[arg-type]


@pytest.mark.parametrize(("field", "value", "match"), [
    ("type", "akaze", "type='akaze' is not one of sift, rootsift, orb, surf"),
    ("max_features", -1, "max_features=-1"),
    ("orb_scale_factor", 1.0, "orb_scale_factor=1.0"),
    ("orb_fast_threshold", 300, "orb_fast_threshold=300"),
    ("sift_sigma", 0.0, "sift_sigma=0.0"),
    ("sift_first_octave", 1, r"sift_first_octave=1 must be one of \(-1, 0\)"),
    ("sift_first_octave", -2, "sift_first_octave=-2"),
    ("sift_first_octave", 0.0, "sift_first_octave=0.0"),
    ("sift_first_octave", False, "sift_first_octave=False"),
    ("sift_double_below_pixels", -1, r"sift_double_below_pixels=-1 must be an int >= 0"),
    ("sift_double_below_pixels", 1.5, "sift_double_below_pixels=1.5"),
    ("sift_double_below_pixels", True, "sift_double_below_pixels=True"),
])
def test_config_validation_names_field(field: str, value: object, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        FeatureConfig(**{field: value})  # type: ignore[arg-type]


def test_config_round_trip_and_unknown_fields() -> None:
    config = FeatureConfig(type="orb", max_features=123)
    assert FeatureConfig.from_dict(config.to_dict()) == config
    octave_zero = FeatureConfig(sift_first_octave=0)
    assert FeatureConfig.from_dict(octave_zero.to_dict()) == octave_zero
    older = {k: v for k, v in FeatureConfig().to_dict().items() if k != "sift_first_octave"}
    assert FeatureConfig.from_dict(older).sift_first_octave == -1  # settings saved before it: OpenCV's doubling
    # saved before the pixel limit: the model's vocabulary was made from every image doubled, so stay so
    before_limit = {k: v for k, v in FeatureConfig().to_dict().items() if k != "sift_double_below_pixels"}
    assert FeatureConfig.from_dict(before_limit).sift_double_below_pixels == 0
    assert not FeatureConfig.from_dict(before_limit).starts_at_octave_zero((2000, 2000))
    with pytest.raises(ConfigError, match="unknown field"):
        FeatureConfig.from_dict({"typ": "sift"})
    with pytest.raises(ConfigError, match="unknown feature type 'akaze'"):
        descriptor_length("akaze")


def test_surf_unavailable_raises_config_error_naming_alternatives(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(features_module, "surf_available", lambda: False)
    features_module._detector.cache_clear()
    config = FeatureConfig(type="surf", surf_extended=False)
    assert descriptor_length(config) == 64 and descriptor_length("surf") == 128
    with pytest.raises(ConfigError, match=r"xfeatures2d.*use type 'sift'.*'orb'"):
        check_feature_config(config)
    with pytest.raises(ConfigError, match="xfeatures2d"):
        extract_features(_textured(), config)
    features_module._detector.cache_clear()


def test_surf_where_available() -> None:
    if not surf_available():
        pytest.skip("this OpenCV has no non-free SURF")
    features = extract_features(_textured(), FeatureConfig(type="surf", max_features=20))
    assert features.descriptors.shape[1] == 128 and len(features) <= 20


def test_compact_descriptors_is_lossless_and_only_bytes_when_exact() -> None:
    from aefabmap_ros.features.extraction import compact_descriptors, restore_descriptors

    integers = np.array([[0.0, 17.0, 255.0]], np.float32)
    compact = compact_descriptors(integers)
    assert compact.dtype == np.uint8
    restored = restore_descriptors(compact, "sift")
    assert restored.dtype == np.float32
    np.testing.assert_array_equal(restored, integers)
    for not_a_byte in ([[0.25, 1.0, 2.0]], [[-1.0, 0.0, 0.0]], [[256.0, 0.0, 0.0]]):
        values = np.array(not_a_byte, np.float32)
        assert compact_descriptors(values).dtype == np.float32
    orb = np.array([[1, 2, 3]], np.uint8)
    assert restore_descriptors(compact_descriptors(orb), "orb").dtype == np.uint8


@pytest.mark.parametrize("kind", ["sift", "rootsift"])
def test_real_descriptors_pass_the_value_check(kind: str) -> None:
    features = extract_features(_textured(3), FeatureConfig(type=kind))
    assert len(features.descriptors) > 10
    check_descriptor_values(features.descriptors, kind)  # what the extractor makes is never refused


@pytest.mark.parametrize(("kind", "value", "match"), [
    ("sift", 3e38, "outside \\[-512, 512\\].*largest magnitude 3e\\+38"),
    ("sift", -600.0, "outside"),
    ("rootsift", 1.5, "outside \\[-1, 1\\]"),
    ("surf", 2.0, "outside"),
    ("sift", np.nan, "1 NaN/Inf sift"),
    ("rootsift", -np.inf, "NaN/Inf"),
])
def test_descriptor_values_no_extractor_makes_are_refused(kind: str, value: float, match: str) -> None:
    descriptors = np.full((3, 128), 0.1, np.float32)
    descriptors[1, 5] = value
    with pytest.raises(DataError, match=match):
        check_descriptor_values(descriptors, kind)
