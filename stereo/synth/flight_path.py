"""How a synthetic flight moves: its options, its timing and the camera's path toward one cut point.

The camera approaches a *target* cut point C along the straight line from the scene camera
(where the tree was drawn from) through C: unit direction `a = C/|C|`. At time t (s) the nominal
left camera sits `d(t) = start_m − speed·t` metres short of C on that line, looking along `a`
with no roll (its y axis is gravity projected across `a`). On top of that:

- lateral sway: `sway_m · sin(2π·sway_hz·t)` along the camera's nominal x axis (zero at t = 0,
  so the first frame is on the approach line; the distance *along* the approach stays d(t));
- attitude jitter: yaw, pitch and roll (about the camera's y, x and z axes) each a smooth random
  wobble within ±`jitter_deg` (three sinusoids of 0.3–2 Hz with random phases from the seed);
- yaw sweep: the camera turns about the vertical (gravity) axis through its own centre at a
  constant `yaw_rate_dps`, first to one side; it turns back on reaching ±`YAW_BOUND_DEG` (a
  triangle wave starting at 0), so the target, on the optical axis at 0, never leaves the middle
  of the image (a ZED Mini sees ±45° across) while the turn rate stays what the vehicle flies.
  It rotates the view only: the position, and so the distance along the approach, is unchanged;
- exposure: a gain factor `1 + exposure · w(t)` with a slow wobble w (0.1–0.5 Hz) within ±1.

Timing: frame i is captured at `t_i = i / fps`. Either `frames` is given (the distance falls
evenly from `start_m` at frame 0 to `end_m` at the last frame), or `speed_mps` is (default
`DEFAULT_SPEED_MPS`): frames are taken while `d(t) ≥ end_m`, so the last one lies at most one
frame's travel short of `end_m` and never beyond it. Giving both is refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from stereo.synth.options import SynthOptions
from stereo.synth.primitives import cross3, unit

#: Approach speed (m/s) when neither `frames` nor `speed_mps` is given: mid of the 0.3–0.5 m/s a
#: pruning drone closes at.
DEFAULT_SPEED_MPS = 0.4
#: Capture time of frame 0 (ns): a fixed start, so a sequence's timestamps depend on its options only.
FIRST_TIMESTAMP_NS = 1_000_000_000
#: How far (degrees) the yaw sweep turns either side of the approach before turning back: the
#: target then stays within the middle third of a ZED Mini image's width.
YAW_BOUND_DEG = 15.0
_JITTER_HZ = (0.3, 2.0)
_EXPOSURE_HZ = (0.1, 0.5)


def _check(ok: bool, name: str, value: object, expected: str) -> None:
    """Raise ValueError naming the option, its value and what is accepted, unless `ok`."""
    if not ok:
        raise ValueError(f"flight option {name} is {value!r}; expected {expected}")


def _finite(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class FlightOptions:
    """Everything that decides a synthetic flight sequence (same options → identical frames).

    Distances in metres, speeds in m/s, frequencies in Hz, angles in degrees. `width`×`height`:
    image size (ZED Mini rig scaled to it). `exposure`: relative gain wobble (0.2 → ±20 %).
    `motion_blur`: blur each view along its image motion over the last `shutter` of the frame
    interval. `yaw_rate_dps`: the yaw sweep's turn rate, °/s (0: none). `foliage`: sparse leaves on
    the twigs (off: a bare tree). `supersample`: rays per pixel side for the images (1 keeps an
    HD720 frame under a second on 2 cores; truth always comes from the pixel-centre ray).
    `noise_std`: sensor noise, grey levels. `threads`: render threads (1–3; the result does not
    depend on it).
    """

    frames: int | None = None
    fps: float = 15.0
    width: int = 1280
    height: int = 720
    start_m: float = 3.0
    end_m: float = 0.8
    speed_mps: float | None = None
    sway_m: float = 0.0
    sway_hz: float = 0.5
    jitter_deg: float = 0.0
    yaw_rate_dps: float = 0.0
    exposure: float = 0.0
    motion_blur: bool = False
    shutter: float = 0.5
    foliage: bool = False
    seed: int = 0
    supersample: int = 1
    noise_std: float = 1.0
    cut_offset_m: float = 0.05
    threads: int = 2

    def __post_init__(self) -> None:
        _check(_finite(self.fps) and 0 < self.fps <= 240, "fps", self.fps, "a frame rate in (0, 240] Hz")
        for name in ("width", "height"):
            value = getattr(self, name)
            _check(isinstance(value, int) and 16 <= value <= 8192, name, value, "an integer from 16 to 8192 px")
        _check(
            _finite(self.end_m) and 0.2 <= self.end_m,
            "end_m",
            self.end_m,
            "a distance ≥ 0.2 m (the generator keeps branches ≥ 0.3 m from its camera)",
        )
        _check(
            _finite(self.start_m) and self.end_m < self.start_m <= 10.0,
            "start_m",
            self.start_m,
            f"a distance above end_m = {self.end_m} m and at most 10 m",
        )
        if self.frames is not None:
            _check(
                isinstance(self.frames, int) and 2 <= self.frames <= 100_000,
                "frames",
                self.frames,
                "an integer from 2 to 100000",
            )
            _check(
                self.speed_mps is None,
                "speed_mps",
                self.speed_mps,
                "None when frames is given (the speed follows from frames, fps and the distances)",
            )
        if self.speed_mps is not None:
            _check(_finite(self.speed_mps) and self.speed_mps > 0, "speed_mps", self.speed_mps, "a speed > 0 m/s")
            _check(
                self.frame_count >= 2,
                "speed_mps",
                self.speed_mps,
                f"a speed slow enough for 2 frames over {self.start_m - self.end_m:g} m at {self.fps:g} fps",
            )
        _check(_finite(self.sway_m) and 0 <= self.sway_m <= 1.0, "sway_m", self.sway_m, "an amplitude in [0, 1] m")
        _check(_finite(self.sway_hz) and 0 < self.sway_hz <= 5.0, "sway_hz", self.sway_hz, "a frequency in (0, 5] Hz")
        _check(
            _finite(self.jitter_deg) and 0 <= self.jitter_deg <= 15.0,
            "jitter_deg",
            self.jitter_deg,
            "an amplitude in [0, 15] degrees",
        )
        _check(
            _finite(self.yaw_rate_dps) and 0 <= self.yaw_rate_dps <= 180.0,
            "yaw_rate_dps",
            self.yaw_rate_dps,
            "a turn rate in [0, 180] degrees per second",
        )
        _check(
            _finite(self.exposure) and 0 <= self.exposure <= 0.9,
            "exposure",
            self.exposure,
            "a relative gain amplitude in [0, 0.9]",
        )
        _check(
            _finite(self.shutter) and 0 < self.shutter <= 1.0,
            "shutter",
            self.shutter,
            "a fraction of the frame interval in (0, 1]",
        )
        _check(isinstance(self.seed, int) and self.seed >= 0, "seed", self.seed, "an integer ≥ 0")
        _check(self.supersample in (1, 2, 3, 4), "supersample", self.supersample, "1, 2, 3 or 4 rays per pixel side")
        _check(
            _finite(self.noise_std) and 0 <= self.noise_std <= 20,
            "noise_std",
            self.noise_std,
            "a sensor noise in [0, 20] grey levels",
        )
        _check(
            _finite(self.cut_offset_m) and 0 <= self.cut_offset_m <= 0.15,
            "cut_offset_m",
            self.cut_offset_m,
            "an offset in [0, 0.15] m from the branch base",
        )
        _check(self.threads in (1, 2, 3), "threads", self.threads, "1, 2 or 3")

    def synth_options(self) -> SynthOptions:
        """The scene generator's options for this flight (bare tree or sparse leaves, no view gain jitter change)."""
        return SynthOptions(
            cut_offset_m=self.cut_offset_m,
            supersample=self.supersample,
            foliage="sparse" if self.foliage else "bare",
            noise_std=self.noise_std,
            threads=self.threads,
        )

    @property
    def speed(self) -> float:
        """Approach speed (m/s): given, implied by `frames`, or `DEFAULT_SPEED_MPS`."""
        if self.frames is not None:
            return (self.start_m - self.end_m) * self.fps / (self.frames - 1)
        return DEFAULT_SPEED_MPS if self.speed_mps is None else self.speed_mps

    @property
    def frame_count(self) -> int:
        """Number of frames: given, or those taken while the distance is still ≥ `end_m`."""
        if self.frames is not None:
            return self.frames
        return int(math.floor((self.start_m - self.end_m) / self.speed * self.fps + 1e-9)) + 1

    def time_s(self, index: int) -> float:
        """Capture time (s after frame 0) of frame `index`."""
        return index / self.fps

    def timestamp_ns(self, index: int) -> int:
        """Capture timestamp (ns) of frame `index`: `FIRST_TIMESTAMP_NS + i/fps`."""
        return FIRST_TIMESTAMP_NS + round(index * 1e9 / self.fps)

    def distance_m(self, time_s: float) -> float:
        """Distance (m) from the nominal camera to the target cut point along the approach at `time_s`."""
        return self.start_m - self.speed * time_s

    def yaw_deg(self, time_s: float) -> float:
        """The yaw sweep's angle (degrees about gravity; + turns the view toward image x) at `time_s`: a
        triangle wave of slope ±`yaw_rate_dps` between ±`YAW_BOUND_DEG`, 0 at t = 0."""
        phase = (self.yaw_rate_dps * time_s + YAW_BOUND_DEG) % (4 * YAW_BOUND_DEG)
        return YAW_BOUND_DEG - abs(phase - 2 * YAW_BOUND_DEG)


class Wobble:
    """A smooth random signal within ±1: a weighted sum of three sinusoids, normalised by the weights."""

    def __init__(self, rng: np.random.Generator, band_hz: tuple[float, float]) -> None:
        self.frequency_hz = rng.uniform(*band_hz, 3)
        self.phase = rng.uniform(0.0, 2 * np.pi, 3)
        self.weight = rng.uniform(0.5, 1.0, 3)

    def __call__(self, time_s: float) -> float:
        waves = np.sin(2 * np.pi * self.frequency_hz * time_s + self.phase)
        return float((self.weight * waves).sum() / self.weight.sum())


def _rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation (3×3) by `angle_rad` about the unit vector `axis` `(3,)` (Rodrigues' formula)."""
    x, y, z = axis
    cross = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + math.sin(angle_rad) * cross + (1 - math.cos(angle_rad)) * cross @ cross


def _axis_rotation(axis: int, angle_rad: float) -> np.ndarray:
    """Rotation (3×3) by `angle_rad` about coordinate axis `axis` (0 = x, 1 = y, 2 = z)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    rotation = np.eye(3)
    rotation[i, i], rotation[i, j], rotation[j, i], rotation[j, j] = c, -s, s, c
    return rotation


class ApproachPath:
    """The camera's pose over time in the scene frame, approaching the cut point `target_m`.

    `down` `(3,)`: gravity in the scene frame (sets the nominal roll). `rng` draws the jitter
    and exposure wobbles. Poses are `(rotation, position)`: `X_scene = rotation · X_cam + position`.
    """

    def __init__(
        self, target_m: np.ndarray, down: np.ndarray, options: FlightOptions, rng: np.random.Generator
    ) -> None:
        self.options = options
        self.target = np.asarray(target_m, dtype=np.float64)
        self.approach = unit(self.target)
        self.down = unit(down)
        y = unit(down - (down @ self.approach) * self.approach)
        self.nominal = np.stack([cross3(y, self.approach), y, self.approach], axis=1)
        self.jitter = [Wobble(rng, _JITTER_HZ) for _ in range(3)]
        self.exposure_wobble = Wobble(rng, _EXPOSURE_HZ)

    def pose(self, time_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(rotation `(3, 3)`, position `(3,)` m) of the left camera at `time_s`, scene frame."""
        opts = self.options
        sway = opts.sway_m * math.sin(2 * math.pi * opts.sway_hz * time_s)
        position = self.target - opts.distance_m(time_s) * self.approach + sway * self.nominal[:, 0]
        yaw, pitch, roll = (math.radians(opts.jitter_deg) * wobble(time_s) for wobble in self.jitter)
        attitude = _axis_rotation(1, yaw) @ _axis_rotation(0, pitch) @ _axis_rotation(2, roll)
        sweep = _rotation_about(self.down, math.radians(opts.yaw_deg(time_s)))
        return sweep @ self.nominal @ attitude, position

    def gain_factor(self, time_s: float) -> float:
        """Exposure gain relative to the first frame's auto-exposure at `time_s`: `1 + exposure · w(t)`."""
        return 1.0 + self.options.exposure * self.exposure_wobble(time_s)
