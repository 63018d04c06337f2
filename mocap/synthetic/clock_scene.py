"""Random scenes for synchronisation: machines nobody designed, cameras whose clocks and frame
rates differ, and the true offsets.

A random digging linkage (`mocap.synthetic.machines.random_digger`) digs as a front shovel
(the three classes of PAPER.md) or as an excavator (a backhoe's drag towards the machine),
planned by `mocap.synthetic.motion.plan_session` with its base bouncing. 2-4 random cameras
(`random_cameras`: 10-90 m away, the machine filling 40-90 % of the image) film a stretch of
8-30 s of it, each on its own clock: camera k's frame f shows time ``f / fps_k + offset_k``
on the reference clock (camera 0's, offset 0; DESIGN.md), offsets up to ±0.3 s, frame rates
of one nominal rate (25 or 30 fps) each off by up to ±0.2 % (29.97 against 30 is 0.1 %).
Every camera's pixels are the true markers projected at its own frames' times plus Gaussian
noise of 0.3-1.5 px, some observations missed. All randomness comes through `rng`.

Shapes: C cameras, F frames, M markers, J joints.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.core.calibration import Calibration, joints_to_table
from mocap.core.camera import Camera
from mocap.core.machine import Machine
from mocap.core.tracks import Tracks, concatenate
from mocap.errors import InputError
from mocap.synthetic.machines import SceneOptions, random_cameras, random_digger
from mocap.synthetic.motion import DigMotion, plan_session
from mocap.synthetic.paths import BACKHOE, CLASSES

KINDS = ("front shovel", "excavator")


@dataclass(frozen=True)
class ClockOptions:
    """The ranges a clock scene is drawn from: `duration_s` (s) of each camera's recording,
    `noise_px` pixel noise SD per axis, `max_offset_s` the largest |offset| (s), `cameras`
    (least, most), `fps` nominal rates, `fps_spread` each camera's rate off the nominal by
    up to this share, `miss` (least, most) share of observations missed."""

    duration_s: tuple[float, float] = (8.0, 30.0)
    noise_px: tuple[float, float] = (0.3, 1.5)
    max_offset_s: float = 0.3
    cameras: tuple[int, int] = (2, 4)
    fps: tuple[float, ...] = (25.0, 30.0)
    fps_spread: float = 0.002
    miss: tuple[float, float] = (0.0, 0.1)


@dataclass(frozen=True)
class ClockScene:
    """A machine filmed by cameras with their own clocks.

    machine: the exact model; kind: one of KINDS; cameras: C true cameras; fps (C,) frame
    rates; offsets (C,) s, the truth sync should find (0 for the reference, camera 0);
    start_s: the reference clock's time of the reference camera's frame 0 in the plan; duration_s:
    each camera's recording (s);
    noise_px: the pixel noise SD; tracks: every camera's observations on its own frames,
    with the time column ``frame / fps``; joints: (J,) the true joint values at the
    reference camera's frame 0 (what a calibration of that frame reports)."""

    machine: Machine
    kind: str
    cameras: tuple[Camera, ...]
    fps: np.ndarray
    offsets: np.ndarray
    start_s: float
    duration_s: float
    noise_px: float
    tracks: Tracks
    joints: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.cameras)
        if np.shape(self.fps) != (n,) or np.shape(self.offsets) != (n,):
            raise ValueError(f"ClockScene: fps and offsets must be ({n},), got {np.shape(self.fps)} and "
                             f"{np.shape(self.offsets)}")

    def calibration(self) -> Calibration:
        """The true cameras as a calibration file gives them, with the frame-0 joint values
        and no time offsets or frame rates (those are sync's to find)."""
        return Calibration(self.cameras, metadata={"joints": joints_to_table(self.joints, self.machine)})


def clock_scene(rng: np.random.Generator, options: ClockOptions = ClockOptions()) -> ClockScene:
    """A random clock scene (see the module docstring)."""
    kind = KINDS[int(rng.integers(0, len(KINDS)))]
    duration = float(rng.uniform(*options.duration_s))
    machine, plan = _planned(rng, kind, duration + 2 * options.max_offset_s + 1.0)
    start = float(rng.uniform(options.max_offset_s, plan.duration - duration - options.max_offset_s - 0.5))
    n_cameras = int(rng.integers(options.cameras[0], options.cameras[1] + 1))
    nominal = float(options.fps[int(rng.integers(0, len(options.fps)))])
    fps = nominal * (1.0 + rng.uniform(-options.fps_spread, options.fps_spread, n_cameras))
    offsets = np.r_[0.0, rng.uniform(-options.max_offset_s, options.max_offset_s, n_cameras - 1)]
    times = [start + offsets[k] + np.arange(int(duration * fps[k])) / fps[k] for k in range(n_cameras)]
    world = [machine.markers(plan.joints(t), plan.world_from_base(t)) for t in times]  # C x (F_k, M, 3)
    cameras = random_cameras(np.concatenate(world), SceneOptions(cameras=(n_cameras, n_cameras)), rng)
    noise = float(rng.uniform(*options.noise_px))
    miss = float(rng.uniform(*options.miss))
    tracks = concatenate([_observe(camera, machine, points, fps[k], noise, miss, rng)
                          for k, (camera, points) in enumerate(zip(cameras, world))])
    first = plan.joints(np.array([start]))[0]  # (J,) at the reference camera's frame 0
    return ClockScene(machine, kind, cameras, fps, offsets, start, duration, noise, tracks, first)


def _planned(rng: np.random.Generator, kind: str, least_s: float) -> tuple[Machine, DigMotion]:
    """A random digger and a plan of it lasting at least `least_s` s; a linkage that cannot
    reach its digs is drawn again."""
    classes = CLASSES if kind == KINDS[0] else (BACKHOE,)
    for _ in range(50):
        machine = random_digger(rng)
        try:
            plan = plan_session(machine, 1, rng, classes=classes)
            while plan.duration < least_s:
                plan = plan_session(machine, len(plan.cycles) + 1, rng, classes=classes)
        except InputError:
            continue
        return machine, plan
    raise RuntimeError("no random digger of 50 reaches its digs")


def _observe(camera: Camera, machine: Machine, world: np.ndarray, fps: float, noise_px: float, miss: float,
             rng: np.random.Generator) -> Tracks:
    """One camera's tracks of the markers' world positions (F, M, 3) at its frames 0..F-1:
    projected, noisy, in the image, some missed."""
    uv = camera.project(world)
    uv = uv + rng.normal(0.0, noise_px, uv.shape)
    w, h = camera.size
    seen = np.all(np.isfinite(uv), axis=-1) & (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1)
    seen &= (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1) & (rng.random(seen.shape) >= miss)
    f, m = np.nonzero(seen)
    return Tracks.from_rows(np.full(len(f), camera.name, dtype=object), f,
                            np.asarray(machine.marker_names, dtype=object)[m], uv[f, m], f / fps)
