"""The parameters of one synthetic sequence (``SynthConfig``), its routes and presets."""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

from aefabmap_ros.errors import ConfigError
from aefabmap_ros.io.config_files import coerce_like

ROUTES = ("figure-eight", "dense-video")
GRID_COLUMNS, GRID_ROWS = 4, 3  # city blocks


@dataclass(frozen=True)
class SynthConfig:
    """Parameters of one synthetic sequence (flat, so they can be ROS parameters or CLI flags)."""

    seed: int = field(default=0, metadata={"description": "Seed of the world, route jitter and camera noise."})
    num_frames: int = field(default=400, metadata={"description": "Frames over the whole route (all laps)."})
    width: int = field(default=640, metadata={"description": "Image width in pixels."})
    height: int = field(default=480, metadata={"description": "Image height in pixels."})
    fov_deg: float = field(default=60.0, metadata={"description": "Horizontal field of view in degrees."})
    color: bool = field(default=False, metadata={"description": "Render bgr8 instead of mono8 images."})
    laps: int = field(default=2, metadata={"description": "How many times the figure-eight route is driven."})
    block_size_m: float = field(default=12.0, metadata={"description": "Side of a city block in metres."})
    street_width_m: float = field(default=8.0, metadata={"description": "Street width, wall to wall, metres."})
    camera_height_m: float = field(default=1.6, metadata={"description": "Camera height above ground, metres."})
    lane_offset_m: float = field(
        default=1.0, metadata={"description": "Mean distance of the route right of the street centre line."}
    )
    lap_lateral_offset_m: float = field(
        default=0.6, metadata={"description": "Lateral distance between the paths of consecutive laps, metres."}
    )
    heading_jitter_deg: float = field(
        default=4.0, metadata={"description": "Std of the slowly varying heading jitter, degrees."}
    )
    speed_variation: float = field(default=0.2, metadata={"description": "Relative std of the slow speed changes."})
    texels_per_m: float = field(default=64.0, metadata={"description": "Texture resolution of route facades."})
    ground_texels_per_m: float = field(default=24.0, metadata={"description": "Texture resolution of the ground."})
    repeated_texture_fraction: float = field(
        default=0.2, metadata={"description": "Fraction of route facades reusing a shared texture (aliasing)."}
    )
    lighting_variation: float = field(
        default=0.25, metadata={"description": "Amplitude of global gain and gamma changes (0 = constant)."}
    )
    sun_drift_deg: float = field(default=120.0, metadata={"description": "Sun azimuth change over the sequence."})
    noise_sigma: float = field(default=3.0, metadata={"description": "Std of Gaussian pixel noise, grey levels."})
    blur_probability: float = field(
        default=0.1, metadata={"description": "Probability that a frame gets horizontal motion blur."}
    )
    max_blur_px: int = field(default=9, metadata={"description": "Longest motion-blur kernel, pixels."})
    fog_distance_m: float = field(
        default=150.0, metadata={"description": "Distance at which haze hides 63 % of a surface, metres."}
    )
    frame_rate_hz: float = field(default=10.0, metadata={"description": "Frame rate of the stamps."})
    start_stamp_ns: int = field(
        default=1_700_000_000_000_000_000, metadata={"description": "Stamp of the first frame, nanoseconds."}
    )
    gt_max_distance_m: float = field(
        default=2.5, metadata={"description": "Ground truth: largest camera-centre distance of a revisit."}
    )
    gt_max_angle_deg: float = field(
        default=30.0, metadata={"description": "Ground truth: largest optical-axis angle of a revisit."}
    )
    gt_min_gap_frames: int = field(
        default=10, metadata={"description": "Pose-rule ground truth: smallest frame gap of a revisit."}
    )
    gt_min_gap_s: float = field(
        default=5.0, metadata={"description": "Covisibility ground truth: smallest time gap of a revisit, s."}
    )
    route: str = field(
        default="figure-eight",
        metadata={"description": "figure-eight (driven `laps` times) or dense-video (one drive with a stop, "
                                 "revisits in both directions and a street never revisited; ignores laps)."},
    )

    def __post_init__(self) -> None:
        self._check_types()
        self._check_ranges()

    def _check_types(self) -> None:
        for item in fields(self):
            value = coerce_like(getattr(self, item.name), item.default)
            object.__setattr__(self, item.name, value)
            expected = type(item.default)
            if type(value) is not expected:
                raise ConfigError(f"{item.name} must be {expected.__name__}, got {value!r}")

    def _check_ranges(self) -> None:
        positive = ("num_frames", "width", "height", "laps", "block_size_m", "street_width_m", "camera_height_m",
                    "texels_per_m", "ground_texels_per_m", "fog_distance_m", "frame_rate_hz",
                    "gt_min_gap_frames", "max_blur_px")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0, got {getattr(self, name)!r}")
        non_negative = ("noise_sigma", "heading_jitter_deg", "lap_lateral_offset_m", "gt_max_distance_m",
                        "sun_drift_deg", "start_stamp_ns", "gt_min_gap_s")
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise ConfigError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        for name in ("repeated_texture_fraction", "blur_probability"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"{name} must be in [0, 1], got {getattr(self, name)!r}")
        for name in ("lighting_variation", "speed_variation"):
            if not 0 <= getattr(self, name) < 1:
                raise ConfigError(f"{name} must be in [0, 1), got {getattr(self, name)!r}")
        if self.route not in ROUTES:
            raise ConfigError(f"route must be one of {sorted(ROUTES)}, got {self.route!r}")
        if not 10 <= self.fov_deg <= 150:
            raise ConfigError(f"fov_deg must be in [10, 150], got {self.fov_deg!r}")
        if not 0 <= self.gt_max_angle_deg <= 180:
            raise ConfigError(f"gt_max_angle_deg must be in [0, 180], got {self.gt_max_angle_deg!r}")
        if self.width < 16 or self.height < 16:
            raise ConfigError(f"width and height must be >= 16, got {self.width}x{self.height}")
        if not self.camera_height_m < 4.0:
            raise ConfigError(f"camera_height_m must be < 4 (below the lowest facade), got {self.camera_height_m!r}")
        if not abs(self.lane_offset_m) + self.lap_lateral_offset_m / 2 < self.street_width_m / 2 - 1.0:
            raise ConfigError(
                f"lane_offset_m {self.lane_offset_m!r} with lap_lateral_offset_m {self.lap_lateral_offset_m!r} "
                f"puts the camera within 1 m of the walls of a street_width_m {self.street_width_m!r} street"
            )




def train_test_configs(config: SynthConfig) -> tuple[SynthConfig, SynthConfig]:
    """(train, test): the training town is another world (seed + 1000003), so the two are disjoint."""
    return replace(config, seed=config.seed + 1_000_003), config



def dense_video_config(*, seed: int = 0, width: int = 320, height: int = 240, num_frames: int = 3600) -> SynthConfig:
    """The dense-video preset: 2 minutes of 30 Hz video along the dense-video route (about 315 m: slow,
    fast, a 4 s stop, a revisit in the same and one in the opposite direction, a street never
    revisited). 320x240 by default: see aefabmap_synth's help for why."""
    return SynthConfig(seed=seed, num_frames=num_frames, width=width, height=height, route="dense-video",
                       frame_rate_hz=30.0, laps=1, gt_min_gap_frames=150, blur_probability=0.05)
