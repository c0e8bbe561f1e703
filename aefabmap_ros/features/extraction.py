"""Local feature extraction: keypoints + descriptors from a grayscale image.

SIFT (128-d float) is the default stand-in for the paper's 128-d SURF, which no
PyPI OpenCV build ships; RootSIFT is SIFT with Hellinger normalisation; ORB is the
binary option (32 bytes). SURF is used only where ``cv2.xfeatures2d`` really
provides it (an OpenCV built with the non-free contrib modules).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, fields
from typing import Any

import cv2
import numpy as np

from aefabmap_ros.errors import ConfigError, DataError, ImageError
from aefabmap_ros.features.descriptors import kind_of_type
from aefabmap_ros.features.kinds import DESCRIPTOR_LENGTHS, FEATURE_TYPES

# The largest |value| each float descriptor type can hold: a SIFT row is scaled to L2 norm 512 (OpenCV,
# VLFeat; OpenCV then saturates to bytes, 0-255), so no element passes 512; RootSIFT is the square root of
# an L1-normalised non-negative row and SURF an L2-normalised row (<= 1 both). A value beyond (e.g. 3e38)
# is no descriptor: it would become some word (the autoencoder) or overflow k-means' distances into a
# confusing range error.
_DESCRIPTOR_VALUE_BOUNDS = {"sift": 512.0, "rootsift": 1.0, "surf": 1.0}
_BOUND_TOLERANCE = 1.001  # float32 rounding of a normalised row may pass 1 by an ulp or two

# SIFT's first octave: -1 = OpenCV's only behaviour (the image doubled), 0 = VLFeat's default (see
# _detect_from_octave_zero for how OpenCV is made to start there).
SIFT_FIRST_OCTAVES = (-1, 0)
# Doubling the image (first octave -1) is for small images: Lowe doubled his to find about four times as
# many stable keypoints. From 640x480 (a VGA camera, 307,200 pixels) up the image itself holds enough: the
# doubled octave takes about two thirds of SIFT's CPU there (79 against 29 ms per 640x480 image) and keeps
# a 30 Hz camera out of reach on two cores, so larger images start at octave 0 by default.
SIFT_DOUBLE_BELOW_PIXELS = 640 * 480


@dataclass(frozen=True)
class FeatureConfig:
    """Which local feature to extract and the detector's thresholds (flat: one ROS parameter each)."""

    type: str = field(
        default="sift",
        metadata={"description": "Feature type: sift (default), rootsift, orb, or surf (needs OpenCV contrib "
                  "with non-free modules)."},
    )
    max_features: int = field(
        default=1000,
        metadata={"description": "Keep at most this many keypoints per image, the strongest by response "
                  "(0 = no limit)."},
    )
    sift_contrast_threshold: float = field(
        default=0.04,
        metadata={"description": "SIFT/RootSIFT contrast threshold: larger keeps fewer, stronger keypoints."},
    )
    sift_edge_threshold: float = field(
        default=10.0,
        metadata={"description": "SIFT/RootSIFT edge threshold: larger keeps more edge-like keypoints."},
    )
    sift_n_octave_layers: int = field(
        default=3, metadata={"description": "SIFT/RootSIFT layers per octave (Lowe: 3)."}
    )
    sift_sigma: float = field(
        default=1.6, metadata={"description": "SIFT/RootSIFT Gaussian sigma at octave 0."}
    )
    sift_first_octave: int = field(
        default=-1,
        metadata={"description": "SIFT/RootSIFT first octave: -1 doubles the image first (Lowe, OpenCV), for "
                  "images under sift_double_below_pixels; 0 starts at the image's own resolution (VLFeat's "
                  "default): about 4x less pyramid work, no keypoints finer than the image's pixels."},
    )
    sift_double_below_pixels: int = field(
        default=SIFT_DOUBLE_BELOW_PIXELS,
        metadata={"description": "With sift_first_octave -1, only images of fewer pixels than this are doubled; "
                  "larger ones start at their own resolution (octave 0): from 640x480 up the doubled octave "
                  "costs two thirds of SIFT's CPU (0 = every image doubled, as OpenCV does)."},
    )
    orb_scale_factor: float = field(
        default=1.2, metadata={"description": "ORB pyramid decimation ratio (> 1)."}
    )
    orb_n_levels: int = field(default=8, metadata={"description": "ORB pyramid levels."})
    orb_fast_threshold: int = field(
        default=20, metadata={"description": "ORB FAST corner threshold (intensity difference, 0-255)."}
    )
    orb_edge_threshold: int = field(
        default=31, metadata={"description": "ORB border in pixels where no keypoint is detected."}
    )
    surf_hessian_threshold: float = field(
        default=400.0, metadata={"description": "SURF Hessian threshold: larger keeps fewer keypoints."}
    )
    surf_extended: bool = field(
        default=True, metadata={"description": "SURF 128-d descriptors (true, as in the paper) or 64-d."}
    )
    surf_upright: bool = field(
        default=False, metadata={"description": "SURF without orientation (U-SURF)."}
    )

    def __post_init__(self) -> None:
        if self.type not in FEATURE_TYPES:
            raise ConfigError(f"FeatureConfig.type={self.type!r} is not one of {', '.join(FEATURE_TYPES)}")
        _require(self.max_features >= 0, "max_features", self.max_features, ">= 0")
        _require(self.sift_contrast_threshold >= 0, "sift_contrast_threshold", self.sift_contrast_threshold,
                 ">= 0")
        _require(self.sift_edge_threshold > 0, "sift_edge_threshold", self.sift_edge_threshold, "> 0")
        _require(self.sift_n_octave_layers >= 1, "sift_n_octave_layers", self.sift_n_octave_layers, ">= 1")
        _require(self.sift_sigma > 0, "sift_sigma", self.sift_sigma, "> 0")
        _require(type(self.sift_first_octave) is int and self.sift_first_octave in SIFT_FIRST_OCTAVES,
                 "sift_first_octave", self.sift_first_octave, f"one of {SIFT_FIRST_OCTAVES}")
        _require(type(self.sift_double_below_pixels) is int and self.sift_double_below_pixels >= 0,
                 "sift_double_below_pixels", self.sift_double_below_pixels, "an int >= 0")
        _require(self.orb_scale_factor > 1.0, "orb_scale_factor", self.orb_scale_factor, "> 1")
        _require(self.orb_n_levels >= 1, "orb_n_levels", self.orb_n_levels, ">= 1")
        _require(0 <= self.orb_fast_threshold <= 255, "orb_fast_threshold", self.orb_fast_threshold,
                 "in [0, 255]")
        _require(self.orb_edge_threshold >= 0, "orb_edge_threshold", self.orb_edge_threshold, ">= 0")
        _require(self.surf_hessian_threshold >= 0, "surf_hessian_threshold", self.surf_hessian_threshold,
                 ">= 0")

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> FeatureConfig:
        """Build from a dict (e.g. model metadata), naming unknown keys."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"FeatureConfig: unknown field(s) {unknown}")
        if "sift_double_below_pixels" not in values:
            # Settings saved before the field (a model's feature_config): its SIFT doubled every image.
            values = {**values, "sift_double_below_pixels": 0}
        return cls(**values)

    def starts_at_octave_zero(self, image_shape: tuple[int, ...]) -> bool:
        """Whether SIFT/RootSIFT on an image of this shape starts at octave 0 (not doubling it first)."""
        if self.type not in ("sift", "rootsift"):
            return False
        if self.sift_first_octave == 0:
            return True
        pixels = int(image_shape[0]) * int(image_shape[1])
        return 0 < self.sift_double_below_pixels <= pixels


def _require(ok: bool, name: str, value: object, rule: str) -> None:
    if not ok:
        raise ConfigError(f"FeatureConfig.{name}={value!r} must be {rule}")


@dataclass(frozen=True)
class Features:
    """Keypoints and descriptors of one image."""

    keypoints: np.ndarray  # (N, 5) float32 [x, y, size, angle, response]
    descriptors: np.ndarray  # (N, D) float32 (sift/rootsift/surf) or uint8 (orb)
    descriptor_type: str

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])


def descriptor_length(feature: str | FeatureConfig) -> int:
    """Row length D of a descriptor type: 128 for sift/rootsift/surf (64 for non-extended SURF), 32 for orb."""
    if isinstance(feature, FeatureConfig):
        if feature.type == "surf":
            return 128 if feature.surf_extended else 64
        return DESCRIPTOR_LENGTHS[feature.type]
    if feature == "surf":
        return 128
    if feature not in DESCRIPTOR_LENGTHS:
        raise ConfigError(f"unknown feature type {feature!r}; known: {', '.join(FEATURE_TYPES)}")
    return DESCRIPTOR_LENGTHS[feature]


def descriptor_dtype(feature: str | FeatureConfig) -> type[np.generic]:
    """numpy dtype of a descriptor type's rows: uint8 for orb, float32 otherwise."""
    name = feature.type if isinstance(feature, FeatureConfig) else feature
    descriptor_length(name)  # validates the name
    return kind_of_type(name).dtype


def compact_descriptors(descriptors: np.ndarray) -> np.ndarray:
    """The rows as uint8 when that is lossless, else unchanged: the smaller form to send or store.

    OpenCV's SIFT values are integers 0-255 held in float32, so they fit a byte exactly (4x smaller);
    RootSIFT and SURF values are fractions and stay float32. ``restore_descriptors`` undoes this.
    """
    values = np.asarray(descriptors)
    if values.dtype == np.uint8:
        return values
    if values.size and (values.min() < 0 or values.max() > 255 or not np.array_equal(values, np.rint(values))):
        return values
    return values.astype(np.uint8)


def restore_descriptors(values: np.ndarray, descriptor_type: str) -> np.ndarray:
    """Descriptor rows in the dtype their type's consumers expect (``descriptor_dtype``), e.g. uint8
    SIFT from ``compact_descriptors`` back to float32; exact, since the bytes were integers."""
    if descriptor_type not in FEATURE_TYPES:  # not ours to judge here; consumers check the type
        return np.asarray(values)
    return np.asarray(values).astype(descriptor_dtype(descriptor_type), copy=False)


def check_descriptor_values(descriptors: np.ndarray, descriptor_type: str) -> None:
    """Raise DataError for NaN/Inf values, or values beyond what ``descriptor_type``'s extractor produces."""
    values = np.asarray(descriptors)
    if values.dtype == np.uint8 or values.size == 0:  # bytes (ORB, compact SIFT) cannot be out of range
        return
    finite = np.isfinite(values)
    if not finite.all():
        raise DataError(f"{int(np.count_nonzero(~finite))} NaN/Inf {descriptor_type} descriptor values")
    bound = _DESCRIPTOR_VALUE_BOUNDS.get(descriptor_type)
    if bound is None:  # a type of someone else's: its consumer refuses it by name
        return
    magnitudes = np.abs(values)
    outside = magnitudes > bound * _BOUND_TOLERANCE
    if outside.any():
        raise DataError(
            f"{int(np.count_nonzero(outside))} {descriptor_type} descriptor values outside [-{bound:g}, {bound:g}] "
            f"(largest magnitude {float(magnitudes.max()):.3g}): not what a {descriptor_type} extractor produces")


def surf_available() -> bool:
    """True when this OpenCV build really provides SURF (contrib + non-free)."""
    xfeatures2d = getattr(cv2, "xfeatures2d", None)
    if xfeatures2d is None or not hasattr(xfeatures2d, "SURF_create"):
        return False
    try:
        xfeatures2d.SURF_create()
    except cv2.error:  # built with contrib but without OPENCV_ENABLE_NONFREE
        return False
    return True


@functools.lru_cache(maxsize=8)
def _detector(config: FeatureConfig) -> Any:
    """One OpenCV detector per config (creating one costs more than a small image's extraction)."""
    if config.type in ("sift", "rootsift"):
        return cv2.SIFT_create(  # type: ignore[attr-defined]
            nfeatures=config.max_features,
            nOctaveLayers=config.sift_n_octave_layers,
            contrastThreshold=config.sift_contrast_threshold,
            edgeThreshold=config.sift_edge_threshold,
            sigma=config.sift_sigma,
        )
    if config.type == "orb":
        return cv2.ORB_create(  # type: ignore[attr-defined]
            nfeatures=config.max_features if config.max_features > 0 else 1_000_000,
            scaleFactor=config.orb_scale_factor,
            nlevels=config.orb_n_levels,
            edgeThreshold=config.orb_edge_threshold,
            patchSize=31,
            fastThreshold=config.orb_fast_threshold,
        )
    if not surf_available():
        raise ConfigError(
            "FeatureConfig.type='surf' needs cv2.xfeatures2d.SURF_create (OpenCV contrib built with "
            "OPENCV_ENABLE_NONFREE), which this OpenCV does not provide; use type 'sift' (the 128-d float "
            "stand-in), 'rootsift', or 'orb'"
        )
    return cv2.xfeatures2d.SURF_create(  # type: ignore[attr-defined]
        hessianThreshold=config.surf_hessian_threshold,
        extended=config.surf_extended,
        upright=config.surf_upright,
    )


def check_feature_config(config: FeatureConfig) -> None:
    """Fail early (ConfigError) if the config's detector cannot be created here, e.g. SURF unavailable."""
    _detector(config)


def empty_features(config: FeatureConfig) -> Features:
    """A Features with no keypoints and the config's descriptor shape."""
    return Features(
        keypoints=np.zeros((0, 5), np.float32),
        descriptors=np.zeros((0, descriptor_length(config)), descriptor_dtype(config)),
        descriptor_type=config.type,
    )


def extract_features(gray: np.ndarray, config: FeatureConfig) -> Features:
    """Detect keypoints and compute descriptors on a 2-D uint8 image.

    An image without features yields (0, 5) keypoints and (0, D) descriptors.
    """
    if not isinstance(gray, np.ndarray) or gray.ndim != 2 or gray.dtype != np.uint8:
        shape = getattr(gray, "shape", None)
        dtype = getattr(gray, "dtype", type(gray).__name__)
        raise ImageError(f"extract_features needs a 2-D uint8 grayscale image, got shape {shape} dtype {dtype}")
    if gray.size == 0:
        raise ImageError(f"extract_features got an empty image of shape {gray.shape}")
    detector = _detector(config)
    if config.starts_at_octave_zero(gray.shape):
        keypoints, descriptors = _detect_from_octave_zero(detector, gray)
    else:
        keypoints, descriptors = _detect(detector, np.ascontiguousarray(gray))
    if descriptors is None or len(keypoints) == 0:
        return empty_features(config)
    descriptors = np.asarray(descriptors, dtype=descriptor_dtype(config))
    if config.type == "surf" and config.max_features > 0 and len(keypoints) > config.max_features:
        # SURF has no nfeatures option: keep the strongest responses ourselves.
        keep = np.argsort(-keypoints[:, 4], kind="stable")[: config.max_features]
        keypoints, descriptors = keypoints[keep], descriptors[keep]
    if config.type == "rootsift":
        descriptors = rootsift(descriptors)
    return Features(
        keypoints=np.ascontiguousarray(keypoints),
        descriptors=np.ascontiguousarray(descriptors),
        descriptor_type=config.type,
    )


def _detect(detector: Any, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """OpenCV's keypoints as (N, 5) float32 rows [x, y, size, angle, response], and its descriptors."""
    cv_keypoints, descriptors = detector.detectAndCompute(gray, None)
    keypoints = np.array(
        [(k.pt[0], k.pt[1], k.size, k.angle, k.response) for k in cv_keypoints], dtype=np.float32
    ).reshape(-1, 5)
    return keypoints, descriptors


def _detect_from_octave_zero(detector: Any, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """SIFT with its first octave at the image's own resolution (VLFeat's firstOctave 0), from OpenCV's
    SIFT, which always doubles its input first (firstOctave -1) and has no option to stop it.

    It is given the image halved instead (each 2x2 block averaged), so its doubled first octave is back
    at the image's resolution: 4x fewer pixels in the finest octave, the one that costs most. Why this is
    octave 0 of the image up to resampling, in the image's pixels (= the doubled half's): OpenCV assumes
    its input carries 0.5 (input) px of blur, 1.0 px once doubled, and blurs on by sqrt(1.6^2 - 1.0^2) to
    reach sigma 1.6. What it really gets is the camera's 0.5 px, the 2x2 box's 0.58 px and the bilinear
    doubling's 0.87 px, then its 1.25 px: sqrt(0.5^2 + 0.58^2 + 0.87^2 + 1.25^2) = 1.70 px at the first
    level. OpenCV's own octave 0 with the doubling (its level 3.2 px in doubled pixels, built on 1.0 px
    + the same 0.87 px of bilinear doubling, halved) is at sqrt(1.0 + 0.75 + 3.2^2 - 1.0) / 2 = 1.66 px:
    the same scale space to 3 %, so both find the same blobs at the same sizes (a test checks sizes and
    positions of matched keypoints). What halving loses (detail above a quarter cycle per pixel) is what
    a 1.6 px Gaussian removes anyway: it passes exp(-2 pi^2 1.6^2 0.25^2) = 4 % of it. The coarser octaves
    follow from the first, as in VLFeat. Descriptors need no change: they are sampled relative to each
    keypoint's scale and orientation, then normalised. An odd last row or column is cut so the halving
    is exactly 2x.

    Keypoints come back in the image's pixels by x 2 (sizes too). Why not 2x + 0.5, though halved pixel
    i is the centre of image pixels 2i and 2i + 1: OpenCV reports positions in its doubled image divided
    by 2, a quarter input pixel beyond where its bilinear doubling put them (doubled pixel j lies at
    input j/2 - 0.25), so its x is the true x_half + 0.25, and 2 (x_half + 0.25) = the image's x - 0.5
    + 0.5. On blobs at known sub-pixel centres this lands on them without bias (test_extraction checks
    it); OpenCV's own first octave -1 reports them 0.25 px right and down, and is left as it is because
    the vocabularies were made with it.
    """
    height, width = (gray.shape[0] // 2) * 2, (gray.shape[1] // 2) * 2
    if height == 0 or width == 0:  # a one-pixel strip: nothing for SIFT to find at any octave
        return np.zeros((0, 5), np.float32), None
    halved = cv2.resize(gray[:height, :width], (width // 2, height // 2), interpolation=cv2.INTER_AREA)
    keypoints, descriptors = _detect(detector, halved)
    keypoints[:, :3] *= 2.0  # x, y, size
    return keypoints, descriptors


def rootsift(descriptors: np.ndarray) -> np.ndarray:
    """RootSIFT (Arandjelovic & Zisserman 2012): L1-normalise, then element-wise square root.

    Euclidean distance between RootSIFT vectors is the Hellinger kernel on the SIFT
    histograms; rows have unit L2 norm.
    """
    values = np.maximum(np.asarray(descriptors, np.float32), 0.0)
    l1 = values.sum(axis=1, keepdims=True)
    result: np.ndarray = np.sqrt(values / np.maximum(l1, 1e-12)).astype(np.float32)
    return result
