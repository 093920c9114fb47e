"""Parameters of the synthetic scenes (ship ballast tank, furnished room): geometry, camera,
lighting, sensor degradations, views."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from gsfix_online.core.config import rng
from gsfix_online.core.types import Intrinsics

Lighting = Literal["lamps", "headlamp"]
Family = Literal["tank", "room"]

T0_NS = 1_700_000_000 * 1_000_000_000  # stamp of frame 0: stamps_ns = T0_NS + i * 1e9 / fps


@dataclass(frozen=True)
class ShipTankConfig:
    """A synthetic scene seen by a moving camera; deterministic by ``seed``.

    ``family`` picks the scene: ``tank``, one wing / double-bottom compartment of a ship seen by an
    inspection robot (world frame: x along the tank, 0..tank_length; y across, 0..tank_width; z up,
    0..tank_height), or ``room``, a furnished room scanned by a hand-held camera (x along the room,
    0..room_length; y across, 0..room_width; z up, 0..room_height). Every other field applies to both.
    The sensor degradations (exposure, motion blur, depth dropouts, pose drift) are off or mild by
    default; ``gsfix_online.scene.variants`` names realistic settings.
    """

    seed: int = field(
        default=0, metadata=rng(0, 2**31 - 1, "random seed: same seed, identical output")
    )
    family: Family = "tank"  # tank: ship ballast tank; room: furnished indoor room
    # Camera
    width: int = field(default=320, metadata=rng(16, 4096, "image width, pixels"))
    height: int = field(default=240, metadata=rng(16, 4096, "image height, pixels"))
    fov_x_deg: float = field(
        default=75.0, metadata=rng(20.0, 150.0, "horizontal field of view, degrees")
    )
    # Explicit intrinsics (e.g. Replica: 1200x680, fx = fy = 600, cx = 599.5, cy = 339.5)
    fx: float = field(default=0.0, metadata=rng(0.0, 1e5, "focal length x, px; 0 = from fov_x_deg"))
    fy: float = field(default=0.0, metadata=rng(0.0, 1e5, "focal length y, px; 0 = fx"))
    cx: float = field(
        default=0.0, metadata=rng(0.0, 1e5, "principal point x, px; 0 = (width - 1) / 2")
    )
    cy: float = field(
        default=0.0, metadata=rng(0.0, 1e5, "principal point y, px; 0 = (height - 1) / 2")
    )
    n_frames: int = field(default=200, metadata=rng(2, 100_000, "frames along the trajectory"))
    fps: float = field(
        default=10.0, metadata=rng(0.1, 1000.0, "frame rate; stamps are t0 + i / fps")
    )
    # Compartment geometry
    tank_length: float = field(default=6.0, metadata=rng(2.0, 40.0, "length along x, m"))
    tank_width: float = field(default=3.2, metadata=rng(1.8, 20.0, "width along y, m"))
    tank_height: float = field(default=2.6, metadata=rng(1.8, 20.0, "height along z, m"))
    n_web_frames: int = field(
        default=3, metadata=rng(0, 30, "transverse web frames (bays = this + 1)")
    )
    web_hole_width: float = field(
        default=1.1, metadata=rng(0.6, 10.0, "lightening hole width (y), m")
    )
    web_hole_height: float = field(
        default=1.6, metadata=rng(0.6, 10.0, "lightening hole height (z), m")
    )
    # Room geometry (family = room)
    room_length: float = field(default=5.0, metadata=rng(4.0, 12.0, "room length along x, m"))
    room_width: float = field(default=4.0, metadata=rng(3.4, 10.0, "room width along y, m"))
    room_height: float = field(default=2.6, metadata=rng(2.3, 4.0, "room height along z, m"))
    room_loop: float = field(
        default=0.8, metadata=rng(0.25, 1.5, "room: turns of the path around the table")
    )
    mesh_edge: float = field(
        default=0.08, metadata=rng(0.02, 1.0, "max triangle edge of plates, m")
    )
    # Lighting and image
    # lamps: fixed point lamps + ambient, shadowed; headlamp: a light at the camera
    lighting: Lighting = "lamps"
    ambient: float = field(
        default=0.08, metadata=rng(0.0, 2.0, "ambient irradiance (1 = white paint at full level)")
    )
    light_power: float = field(
        default=1.0, metadata=rng(0.0, 100.0, "multiplier on lamp / headlamp intensity")
    )
    grayscale: bool = False  # True: colour images are [H, W] uint8 like the ship rig's cameras
    image_noise: float = field(
        default=1.5, metadata=rng(0.0, 50.0, "colour noise sigma, 8-bit levels")
    )
    # Auto-exposure: a per-frame gain on the light reaching the colour sensor (before the tone
    # curve, noise and 8-bit rounding); ground-truth images stay at gain 1. Off when min = max = 1.
    exposure_gain_min: float = field(
        default=1.0, metadata=rng(0.05, 1.0, "lowest exposure gain (0.7: 30 % less light)")
    )
    exposure_gain_max: float = field(
        default=1.0, metadata=rng(1.0, 20.0, "highest exposure gain (1.4: 40 % more light)")
    )
    exposure_smooth_s: float = field(
        default=2.0, metadata=rng(0.01, 1000.0, "time scale of the smooth gain wander, s")
    )
    exposure_step_prob: float = field(
        default=0.0, metadata=rng(0.0, 1.0, "per-frame probability of a sudden gain step")
    )
    white_balance_sigma: float = field(
        default=0.0,
        metadata=rng(
            0.0,
            0.5,
            "auto white balance: std of each channel's log gain before keeping the brightness",
        ),
    )
    # Motion blur: the colour image integrates the scene over the shutter time, centred on the
    # frame stamp (depth stays sharp: a short global-shutter IR exposure).
    shutter_s: float = field(
        default=0.0, metadata=rng(0.0, 10.0, "shutter time for motion blur, s; 0 = sharp")
    )
    blur_samples: int = field(
        default=0, metadata=rng(0, 256, "blur samples across the shutter; 0 = one per ~1.5 px")
    )
    # Depth sensor
    depth_noise: float = field(
        default=0.0035, metadata=rng(0.0, 0.1, "k in sigma = k z^2 (1/m); D455-like")
    )
    dropout: float = field(
        default=0.02, metadata=rng(0.0, 0.9, "fraction of depth pixels lost in blobs")
    )
    dropout_blob_px: float = field(
        default=3.0, metadata=rng(0.5, 100.0, "dropout blob size (blur sigma), px")
    )
    depth_grazing_deg: float = field(
        default=90.0, metadata=rng(30.0, 90.0, "depth is lost beyond this incidence angle, deg")
    )
    depth_dark_level: float = field(
        default=0.0, metadata=rng(0.0, 255.0, "depth is lost on surfaces darker than this, 8-bit")
    )
    stereo_baseline: float = field(
        default=0.0, metadata=rng(0.0, 1.0, "stereo occlusion holes for this baseline, m; 0 = off")
    )
    depth_min: float = field(default=0.2, metadata=rng(0.0, 5.0, "closer depth is invalid (0), m"))
    depth_max: float = field(
        default=8.0, metadata=rng(0.5, 13.0, "farther depth is invalid (0), m")
    )
    # Pose estimate (VIO-like), written as tum/estimated.txt when not both 0
    pose_drift: float = field(
        default=0.0, metadata=rng(0.0, 1.0, "drift per metre travelled (0.01: ~1 %, ~1 deg/m yaw)")
    )
    pose_noise: float = field(
        default=0.0, metadata=rng(0.0, 1.0, "per-frame position jitter sigma, m")
    )
    pose_noise_deg: float = field(
        default=0.0, metadata=rng(0.0, 30.0, "per-frame rotation jitter sigma, deg")
    )
    # Trajectory
    bays_visited: int = field(
        default=0, metadata=rng(0, 31, "bays the robot enters; 0 = all but the last")
    )
    yaw_sweep_deg: float = field(
        default=40.0, metadata=rng(0.0, 90.0, "amplitude of the yaw sweep, deg")
    )
    pitch_sweep_deg: float = field(
        default=15.0, metadata=rng(0.0, 60.0, "amplitude of the pitch sweep, deg")
    )
    clearance: float = field(
        default=0.3, metadata=rng(0.05, 2.0, "min camera distance to geometry, m")
    )
    # Novel views
    n_novel: int = field(default=8, metadata=rng(0, 1000, "novel (held-out) views"))
    novel_coverage_min: float = field(
        default=0.3, metadata=rng(0.0, 1.0, "min fraction of a novel view seen in training")
    )
    novel_coverage_max: float = field(
        default=0.85, metadata=rng(0.0, 1.0, "max fraction of a novel view seen in training")
    )
    coverage_voxel: float = field(
        default=0.05, metadata=rng(0.005, 1.0, "voxel for the observed-surface set, m")
    )
    novel_candidates: int = field(
        default=400, metadata=rng(1, 100_000, "candidate poses tried for novel views")
    )

    def validate(self) -> None:
        if self.novel_coverage_min >= self.novel_coverage_max:
            raise ValueError(
                f"novel_coverage_min must be < novel_coverage_max, got {self.novel_coverage_min} >= {self.novel_coverage_max}"
            )
        if self.depth_min >= self.depth_max:
            raise ValueError(
                f"depth_min must be < depth_max, got {self.depth_min} >= {self.depth_max}"
            )
        if self.shutter_s * self.fps > 1.0:
            raise ValueError(
                f"shutter_s must not exceed the frame interval 1 / fps = {1.0 / self.fps:.4g} s, got {self.shutter_s}"
            )
        if not (0.0 <= self.cx <= self.width and 0.0 <= self.cy <= self.height):  # 0 = image centre
            raise ValueError(
                f"principal point ({self.cx}, {self.cy}) must lie inside the {self.width}x{self.height} image"
            )
        if self.family != "tank":
            return  # the tank's geometry fields are not used
        bay = self.tank_length / (self.n_web_frames + 1)
        if bay < 1.0:
            raise ValueError(
                f"bays must be at least 1 m long, got {bay:.2f} m ({self.n_web_frames} webs in {self.tank_length} m)"
            )
        if (
            self.web_hole_width > self.tank_width - 1.0
            or self.web_hole_height > self.tank_height - 0.8
        ):
            raise ValueError(
                f"web hole {self.web_hole_width}x{self.web_hole_height} m does not fit a {self.tank_width}x{self.tank_height} m section with margins"
            )
        if self.bays_visited > self.n_web_frames + 1:
            raise ValueError(
                f"bays_visited must be <= {self.n_web_frames + 1} bays, got {self.bays_visited}"
            )

    @property
    def intrinsics(self) -> Intrinsics:
        """``fx``/``fy``/``cx``/``cy`` where set, else square pixels with ``fov_x_deg`` and the
        principal point at the image centre (pixel-centre convention)."""
        fx = self.fx or 0.5 * self.width / math.tan(math.radians(self.fov_x_deg) / 2.0)
        return Intrinsics(
            fx,
            self.fy or fx,
            self.cx or (self.width - 1) / 2.0,
            self.cy or (self.height - 1) / 2.0,
            self.width,
            self.height,
        )

    @property
    def exposure_varies(self) -> bool:
        return self.exposure_gain_min < 1.0 or self.exposure_gain_max > 1.0

    @property
    def white_balance_varies(self) -> bool:
        return self.white_balance_sigma > 0.0 and not self.grayscale  # a mono sensor has no AWB

    @property
    def n_bays(self) -> int:
        return self.n_web_frames + 1

    def stamp_ns(self, i: int) -> int:
        return T0_NS + round(i * 1e9 / self.fps)


# The same parameters serve every scene family; the old name stays for the tank's callers.
SceneConfig = ShipTankConfig
