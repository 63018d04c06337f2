"""Random articulated machines nobody designed by hand, and random scenes of them.

`random_machine_document` writes a machine model as a user's TOML document would: 0-6
moving links on revolute or prismatic joints, links 0.5-20 m long, random origins and
`rpy_deg` (frames turned upside down), joint axes of either sign and not of unit length,
joint names unlike the link names, 1-4 markers per moving link (down to the paper's minimum
of one), 4-8 non-coplanar base markers, a named tip point on the last link and a
`[bucket_angle]` direction that is not a unit vector. `random_scene` puts such a machine in
front of 1-4 random cameras at 10-90 m and observes it with noise, occlusion, gross
outliers and a tape-measured model (every marker coordinate off by up to ±`tolerance`).
All randomness comes through `rng`.

Shapes: F frames, J joints, M markers, C cameras.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mocap.calibration import identify
from mocap.calibration.problem import Observations
from mocap.core.camera import Camera
from mocap.core.machine import Machine
from mocap.core.tracks import Tracks
from mocap.errors import DegenerateError
from mocap.io.machine_toml import machine_from_dict
from mocap.synthetic.scenes import look_at_camera
from mocap.synthetic.session import marker_sizes

IMAGE_SIZES = ((1280, 720), (1920, 1080), (2560, 1440), (3840, 2160))
_WORDS = ("alder", "birch", "cedar", "dogwood", "elm", "fir", "ginkgo", "hazel", "ivy", "juniper")


def random_machine_document(rng: np.random.Generator, n_moving: int | None = None) -> dict:
    """A machine model as a parsed TOML document (see the module docstring)."""
    n_moving = int(rng.integers(0, 7)) if n_moving is None else n_moving
    half = rng.uniform(0.5, 4.0) * np.array([1.0, rng.uniform(0.4, 0.9), rng.uniform(0.2, 0.5)])
    links = [{"name": f"{_WORDS[0]}_frame"}]
    ends = [np.array([0.0, 0.0, 2.0 * half[2]])]  # where a child of each link attaches
    markers = [
        {"name": f"B{k + 1}", "link": links[0]["name"], "position": p.tolist()}
        for k, p in enumerate(_base_markers(rng, half))
    ]
    for i in range(1, n_moving + 1):
        parent = i - 1 if i == 1 or rng.random() < 0.8 else int(rng.integers(0, i))
        length = float(np.exp(rng.uniform(np.log(0.5), np.log(20.0))))
        prismatic = rng.random() < 0.2
        axis = _signed_axis(rng)
        end = _link_end(rng, axis, length, prismatic)
        origin = ends[parent] * rng.uniform(0.6, 1.0) + rng.normal(0.0, 0.05 * length, 3)
        joint = {
            "name": f"q{10 * i + int(rng.integers(0, 10))}",
            "type": "prismatic" if prismatic else "revolute",
            "axis": (axis * rng.uniform(0.5, 2.0)).round(6).tolist(),
            "origin": origin.round(4).tolist(),
            "rpy_deg": _rpy(rng).round(3).tolist(),
            "limits": _limits(rng, length, prismatic),
        }
        name = f"{_WORDS[i % len(_WORDS)]}_{i}"
        links.append({"name": name, "parent": links[parent]["name"], "joint": joint})
        ends.append(end)
        for k in range(int(rng.integers(1, 5))):
            along = end * rng.uniform(0.25, 1.0)
            lateral = _perpendicular(rng, end) * rng.uniform(0.0, 0.15 * length)
            markers.append({"name": f"M{i}{k + 1}", "link": name, "position": (along + lateral).round(4).tolist()})
    last = links[-1]["name"]
    document = {
        "name": f"Random machine {int(rng.integers(0, 10**6)):06d}",
        "source": "mocap.synthetic.machines.random_machine_document",
        "links": links,
        "markers": markers,
        "points": [{"name": "tip", "link": last, "position": (ends[-1] * 1.05).round(4).tolist()}],
        "bucket_angle": {"link": last, "direction": (_unit(ends[-1] + rng.normal(0, 0.1, 3)) * rng.uniform(0.3, 3.0)).round(6).tolist()},
    }
    return document


def random_machine(rng: np.random.Generator, n_moving: int | None = None) -> Machine:
    """A random machine model, built through the model file's own validation."""
    return machine_from_dict(random_machine_document(rng, n_moving), "<random machine>")


def random_digger_document(rng: np.random.Generator) -> dict:
    """A random machine with a digging linkage, as a parsed TOML document: base, a house
    swinging about the vertical (either sense), and boom, arm and bucket turning about the
    house's y axis (either sign) with random proportions (boom 1.5-10 m, arm 0.5-0.7 and
    the tip 0.25-0.45 of it), random pitch of each link frame, links that leave their
    joints at random angles in their own frames, a `[bucket_angle]` direction off the tip's
    by up to 20 deg and of any length, and joint limits around a random working pose of the
    elbow-down kind (the arm hanging forward of the boom). The tip is named `bucket_tip`."""
    deg = np.radians
    boom = float(np.exp(rng.uniform(np.log(1.5), np.log(10.0))))
    lengths = boom * np.array([1.0, rng.uniform(0.5, 0.7), rng.uniform(0.25, 0.45)])
    house = boom * rng.uniform(0.2, 0.35)
    pin = boom * np.array([rng.uniform(0.05, 0.35), rng.uniform(0.05, 0.25)])
    leave = deg(rng.uniform(-20.0, 20.0, 3))  # each link's end seen from its joint, in its own frame
    pose = deg(np.array([35.0, -70.0, 5.0]) + rng.uniform(-10.0, 10.0, 3))  # working pose: each end's direction
    middle = deg(rng.uniform(-40.0, 40.0, 3))  # joint values of that pose
    sign = rng.choice([-1.0, 1.0], 3)  # +1: a positive joint value turns the link up (axis -y)
    frame = pose - leave  # upward angle of each link frame in that pose
    pitch = np.diff(frame, prepend=0.0) - sign * middle  # of each link frame at joint value 0
    half = np.array([70.0, 95.0, 130.0])
    words = rng.permutation(_WORDS)
    names = [f"{words[k]}_{k}" for k in range(5)]
    links = [{"name": names[0]}, {"name": names[1], "parent": names[0], "joint": {
        "name": f"q{int(rng.integers(0, 10))}", "type": "revolute", "axis": [0.0, 0.0, float(rng.choice([-1.0, 1.0]))],
        "origin": [0.0, 0.0, round(house, 4)], "rpy_deg": [0.0, 0.0, 0.0], "limits": [-180.0, 180.0]}}]
    origins = [np.array([pin[0], 0.0, pin[1]])]
    ends = [lengths[k] * np.array([np.cos(leave[k]), 0.0, np.sin(leave[k])]) for k in range(3)]
    origins += ends[:2]
    for k in range(3):
        q = np.degrees(middle[k])
        links.append({"name": names[k + 2], "parent": names[k + 1], "joint": {
            "name": f"q{10 * (k + 2) + int(rng.integers(0, 10))}", "type": "revolute",
            "axis": [0.0, float(-sign[k]), 0.0], "origin": origins[k].round(4).tolist(),
            "rpy_deg": [0.0, round(float(-np.degrees(pitch[k])), 4), 0.0],  # Ry(pitch) turns x downward
            "limits": [round(q - half[k], 3), round(q + half[k], 3)]}})
    markers = [{"name": f"B{k + 1}", "link": names[0], "position": p.tolist()}
               for k, p in enumerate(_base_markers(rng, boom * np.array([0.35, 0.25, 0.12])))]
    apart = 1.5 * marker_sizes(float(lengths.sum()))[1]  # painted squares do not overlap
    for k in range(3):
        first_share = first_side = None
        for m in range(2):
            share = rng.uniform(0.3, 0.9)
            side = np.array([0.0, rng.choice([-1.0, 1.0]) * 0.05 * boom, 0.0])
            if first_share is not None and np.linalg.norm(ends[k] * (share - first_share) + side - first_side) < apart:
                # the second slid along the link from the first, towards the end where there is room
                step = apart / lengths[k]
                share = first_share + step if first_share + step <= 0.95 else first_share - step
            first_share, first_side = share, side
            at = ends[k] * share + side
            markers.append({"name": f"M{k + 1}{m + 1}", "link": names[k + 2], "position": at.round(4).tolist()})
    tilt = deg(rng.uniform(-20.0, 20.0))
    c, s = np.cos(leave[2] + tilt), np.sin(leave[2] + tilt)
    return {
        "name": f"Random digger {int(rng.integers(0, 10**6)):06d}",
        "source": "mocap.synthetic.machines.random_digger_document",
        "links": links,
        "markers": markers,
        "points": [{"name": "bucket_tip", "link": names[4], "position": ends[2].round(4).tolist()}],
        "bucket_angle": {"link": names[4],
                         "direction": (np.array([c, 0.0, s]) * rng.uniform(0.3, 3.0)).round(6).tolist()},
    }


def random_digger(rng: np.random.Generator) -> Machine:
    """A random machine with a digging linkage (`random_digger_document`), through the
    model file's own validation."""
    return machine_from_dict(random_digger_document(rng), "<random digger>")


def _base_markers(rng: np.random.Generator, half: np.ndarray) -> np.ndarray:
    """4-8 points on the faces of the base's box (half sizes `half`), spread in depth."""
    n = int(rng.integers(4, 9))
    while True:
        points = rng.uniform(-1.0, 1.0, (n, 3))
        face = rng.integers(0, 3, n)
        points[np.arange(n), face] = np.sign(points[np.arange(n), face])
        points = points * half + np.array([0.0, 0.0, half[2]])
        s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
        if s[2] > 0.15 * s[0]:
            return points.round(4)


def _signed_axis(rng: np.random.Generator) -> np.ndarray:
    """A joint axis: mostly a link-frame axis of either sign, sometimes any direction."""
    if rng.random() < 0.7:
        axis = np.zeros(3)
        axis[rng.integers(0, 3)] = rng.choice([-1.0, 1.0])
        return axis
    return _unit(rng.normal(size=3))


def _link_end(rng, axis, length, prismatic) -> np.ndarray:
    """The vector (link frame) from the joint to the link's far end: along the axis for a
    prismatic joint, mostly across it for a revolute one (a marker on the axis fixes nothing)."""
    if prismatic:
        return axis * length
    return _perpendicular(rng, axis) * length + axis * rng.uniform(-0.2, 0.2) * length


def _perpendicular(rng, vector) -> np.ndarray:
    v = rng.normal(size=3)
    v -= v @ vector / (vector @ vector) * vector
    return _unit(v)


def _rpy(rng: np.random.Generator) -> np.ndarray:
    """Frames as people write them: none, turned by right angles (upside down), or anything."""
    pick = rng.random()
    if pick < 0.3:
        return np.zeros(3)
    if pick < 0.6:
        return rng.choice([-90.0, 0.0, 90.0, 180.0], 3) + rng.normal(0.0, 10.0, 3) * (rng.random(3) < 0.3)
    return rng.uniform(-180.0, 180.0, 3)


def _limits(rng, length, prismatic) -> list[float]:
    if prismatic:
        return [0.0, round(float(length * rng.uniform(0.3, 0.8)), 4)]
    if rng.random() < 0.15:
        return [-180.0, 180.0]
    width = rng.uniform(60.0, 300.0)
    centre = rng.uniform(-180.0 + width / 2, 180.0 - width / 2)
    return [round(centre - width / 2, 3), round(centre + width / 2, 3)]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


# --- scenes ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class SceneOptions:
    """What a random scene adds to the truth.

    noise_px: pixel noise SD per axis; occlusion: share of observations hidden; outliers:
    share of observations moved by 10-100 px; tolerance: every marker coordinate of the
    user's model off by up to ±tolerance (a fraction, uniform), 0 for the exact model;
    cameras: (least, most) number of cameras; distance_m: camera distances.
    """

    noise_px: float = 0.5
    occlusion: float = 0.0
    outliers: float = 0.0
    tolerance: float = 0.0
    cameras: tuple[int, int] = (1, 4)
    distance_m: tuple[float, float] = (10.0, 90.0)

    @classmethod
    def field(cls) -> SceneOptions:
        """Field conditions: the paper's tape measurement, occlusion and wrong detections."""
        return cls(noise_px=0.8, occlusion=0.15, outliers=0.02, tolerance=0.05)


@dataclass(frozen=True)
class RandomScene:
    """A random machine filmed by random cameras.

    machine: the exact model (the truth); model: the model as measured (tape error);
    cameras: C true cameras; joints: (F, J) true joint values; tracks: the observations;
    outlier: (R,) bool, the tracks' rows moved by a gross error.
    """

    machine: Machine
    model: Machine
    cameras: tuple[Camera, ...]
    joints: np.ndarray
    tracks: Tracks
    outlier: np.ndarray
    options: SceneOptions

    def pixels(self) -> np.ndarray:
        """(C, F, M, 2) the observed pixels, NaN where not seen."""
        names = [c.name for c in self.cameras]
        out = np.full((len(names), len(self.joints), len(self.machine.marker_names), 2), np.nan)
        camera = np.array([names.index(c) for c in self.tracks.camera], dtype=int)
        out[camera, self.tracks.frame, self.machine.marker_index(self.tracks.marker)] = self.tracks.xy
        return out

    def observations(self, frame: int = 0, inliers_only: bool = False) -> Observations:
        """One frame's observations as the calibration takes them."""
        rows = (self.tracks.frame == frame) & ~(self.outlier & inliers_only)
        names = [c.name for c in self.cameras]
        camera = np.array([names.index(c) for c in self.tracks.camera[rows]], dtype=int)
        return Observations(camera, self.machine.marker_index(self.tracks.marker[rows]), self.tracks.xy[rows])


def random_scene(rng: np.random.Generator, options: SceneOptions = SceneOptions(), n_frames: int = 1,
                 machine: Machine | None = None) -> RandomScene:
    """A random machine (or `machine`) moving for `n_frames` frames at 30 fps, seen by
    random cameras; the first frame satisfies the calibration's counts (occlusion is drawn
    again until it does)."""
    machine = random_machine(rng) if machine is None else machine
    joints = random_motion(machine, n_frames, rng)
    world = machine.markers(joints)  # (F, M, 3)
    cameras = random_cameras(world, options, rng)
    for _ in range(100):
        tracks, outlier = _observe(cameras, machine, world, rng, options)
        if _identifiable(machine, cameras, tracks):
            break
    else:
        raise DegenerateError("no occlusion draw leaves the scene identifiable")
    return RandomScene(machine, _measured(machine, rng, options.tolerance), cameras, joints, tracks, outlier, options)


def random_motion(machine: Machine, n_frames: int, rng: np.random.Generator, fps: float = 30.0) -> np.ndarray:
    """(F, J) smooth joint trajectories at `fps` inside the middle 70 % of each joint's
    range: two sines per joint of random phases, slow enough that no joint turns faster
    than 0.4 rad/s or slides faster than 0.5 m/s (a machine's pace)."""
    limits = machine.joint_limits
    low, high = limits[:, 0], limits[:, 1]
    full = machine.wraps
    low = np.where(full, -np.pi / 3, low)
    high = np.where(full, np.pi / 3, high)
    centre, half = (low + high) / 2, 0.35 * (high - low)
    t = np.arange(n_frames)[:, None] / fps
    phase = rng.uniform(0, 2 * np.pi, (2, machine.n_joints))
    top_speed = np.where(np.array([j.type == "revolute" for j in machine.joints], bool), 0.4, 0.5)
    fastest = top_speed / (2 * np.pi * np.maximum(half, 1e-9))  # Hz at which a full-amplitude sine reaches it
    rate = fastest * rng.uniform(0.2, 1.0, (2, machine.n_joints))
    wave = 0.6 * np.sin(2 * np.pi * rate[0] * t + phase[0]) + 0.4 * np.sin(2 * np.pi * rate[1] * t + phase[1])
    return centre + half * wave


def random_cameras(world: np.ndarray, options: SceneOptions, rng: np.random.Generator) -> tuple[Camera, ...]:
    """`options.cameras` (least, most) random cameras named cam1, cam2, ... looking at the
    markers' world positions `world` (F, M, 3) from `options.distance_m`, every marker of
    every frame in front of them and in view."""
    n_cameras = int(rng.integers(options.cameras[0], options.cameras[1] + 1))
    return tuple(_random_camera(f"cam{k + 1}", world, options.distance_m, rng) for k in range(n_cameras))


def _random_camera(name: str, world: np.ndarray, distance_m, rng) -> Camera:
    """A camera looking at the markers' centre from a random direction, far enough that
    every marker of every frame is in front of it, zoomed so they fill 40-90 % of the image."""
    points = world.reshape(-1, 3)
    target = points.mean(axis=0)
    radius = np.linalg.norm(points - target, axis=1).max()
    distance = max(rng.uniform(*distance_m), 2.5 * radius)
    azimuth = rng.uniform(0, 2 * np.pi)
    elevation = np.radians(rng.uniform(3.0, 35.0))
    direction = np.array([np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation), np.sin(elevation)])
    center = target + distance * direction
    size = IMAGE_SIZES[int(rng.integers(0, len(IMAGE_SIZES)))]
    probe = look_at_camera(name, size, 1000.0, center, target, roll=rng.normal(0, 0.03))
    uv = probe.project(points) - probe.matrix[:2, 2]
    spread = np.abs(uv).max(axis=0) / (np.array(size) / 2)  # at f = 1000 px
    focal = 1000.0 * rng.uniform(0.4, 0.9) / max(spread.max(), 1e-9)
    return look_at_camera(name, size, focal, center, target + rng.normal(0, 0.02 * radius, 3), roll=rng.normal(0, 0.03))


def _observe(cameras, machine: Machine, world: np.ndarray, rng, options: SceneOptions):
    rows = []
    for camera in cameras:
        uv = camera.project(world)
        uv = uv + rng.normal(0.0, options.noise_px, uv.shape)
        w, h = camera.size
        seen = np.all(np.isfinite(uv), axis=-1) & (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1)
        seen &= (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1) & (rng.random(seen.shape) >= options.occlusion)
        f, m = np.nonzero(seen)
        rows.append((np.full(len(f), camera.name, dtype=object), f, np.asarray(machine.marker_names, dtype=object)[m], uv[f, m]))
    xy = np.concatenate([r[3] for r in rows])
    outlier = rng.random(len(xy)) < options.outliers
    angle = rng.uniform(0, 2 * np.pi, outlier.sum())
    xy[outlier] += np.c_[np.cos(angle), np.sin(angle)] * rng.uniform(10.0, 100.0, outlier.sum())[:, None]
    tracks = Tracks.from_rows(*(np.concatenate([r[k] for r in rows]) for k in range(3)), xy)
    return tracks, outlier


def _identifiable(machine: Machine, cameras, tracks: Tracks) -> bool:
    """The first frame (the calibration frame) satisfies the calibration's counts with all
    cameras together."""
    names = [c.name for c in cameras]
    index = {n: i for i, n in enumerate(names)}
    rows = tracks.frame == 0
    try:
        identify.check_counts(machine, names, np.array([index[c] for c in tracks.camera[rows]], dtype=int),
                              machine.marker_index(tracks.marker[rows]), False, 7)
    except DegenerateError:
        return False
    return True


def _measured(machine: Machine, rng, tolerance: float) -> Machine:
    """The model as a tape measure gives it: every marker coordinate off by up to ±tolerance."""
    if tolerance == 0:
        return machine
    scale = 1.0 + rng.uniform(-tolerance, tolerance, machine.marker_positions.shape)
    return replace(machine, marker_positions=machine.marker_positions * scale)
