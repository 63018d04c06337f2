"""Building blocks of planned motion: smooth moves, smooth noise, dig paths.

Dig paths are in the house's vertical plane: ``x`` forward from the swing axis, ``z``
height above the ground (m), bucket angle ``beta`` (rad, to the horizontal, positive
upward). Times in seconds, path progress ``u`` in [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mocap.core.classes import DIG_CLASSES

CLASSES = DIG_CLASSES
BACKHOE = "backhoe"  # a backhoe's dig: out at the floor, dragged towards the machine and curled up


def min_jerk(tau: np.ndarray) -> np.ndarray:
    """The minimum-jerk blend 10 τ³ - 15 τ⁴ + 6 τ⁵ of τ clipped to [0, 1]: zero velocity
    and acceleration at both ends."""
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10.0 + tau * (-15.0 + 6.0 * tau))


@dataclass(frozen=True)
class SmoothNoise:
    """A sum of K sinusoids per channel: value(t) = Σ_k a_k sin(2π f_k t + φ_k), (T, D).

    `amplitude` (K, D), `frequency` (K,) Hz, `phase` (K, D) rad.
    """

    amplitude: np.ndarray
    frequency: np.ndarray
    phase: np.ndarray

    def __post_init__(self) -> None:
        k = np.shape(self.frequency)[0]
        shape = np.shape(self.amplitude)
        if np.ndim(self.frequency) != 1 or shape != np.shape(self.phase) or len(shape) != 2 or shape[0] != k:
            raise ValueError(
                f"SmoothNoise needs amplitude and phase (K, D) and frequency (K,), got "
                f"{np.shape(self.amplitude)}, {np.shape(self.phase)}, {np.shape(self.frequency)}"
            )

    @classmethod
    def random(cls, rng: np.random.Generator, sd: np.ndarray, band_hz: tuple[float, float], k: int = 6) -> SmoothNoise:
        """Noise of standard deviation `sd` (D,) per channel with frequencies in `band_hz`."""
        sd = np.atleast_1d(np.asarray(sd, dtype=float))
        amplitude = rng.uniform(0.5, 1.0, (k, sd.size))
        amplitude *= sd * np.sqrt(2.0) / np.sqrt((amplitude**2).sum(axis=0))
        frequency = rng.uniform(*band_hz, k)
        return cls(amplitude, frequency, rng.uniform(0, 2 * np.pi, (k, sd.size)))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        arg = 2 * np.pi * np.asarray(t, dtype=float)[:, None] * self.frequency  # (T, K)
        return np.einsum("tkd,kd->td", np.sin(arg[:, :, None] + self.phase), self.amplitude)


@dataclass(frozen=True)
class DigShape:
    """A dig path: a horizontal push of length `push`, an arc of radius `radius` turning
    up to the direction `climb` (rad above horizontal), a straight rise of length `rise`;
    from `start` (x, z). Bucket angle from `angle0` to `angle1` (rad) with the class's
    profile. `scale` (sx, sz) stretches the path about its start; `forward` -1 runs it
    towards the machine (a backhoe's drag)."""

    label: str
    start: np.ndarray
    push: float
    radius: float
    climb: float
    rise: float
    angle0: float
    angle1: float
    scale: tuple[float, float] = (1.0, 1.0)
    forward: float = 1.0

    @property
    def length(self) -> float:
        return self.push + self.radius * self.climb + self.rise

    def tip(self, u: np.ndarray) -> np.ndarray:
        """Tip (x, z) (T, 2) at progress u (T,) along the path's arc length."""
        s = np.clip(np.asarray(u, dtype=float), 0, 1) * self.length
        arc = self.radius * self.climb
        a = np.clip((s - self.push) / max(self.radius, 1e-12), 0.0, self.climb)
        x = np.minimum(s, self.push) + self.radius * np.sin(a)
        z = self.radius * (1.0 - np.cos(a))
        beyond = np.maximum(s - self.push - arc, 0.0)
        x = x + beyond * np.cos(self.climb)
        z = z + beyond * np.sin(self.climb)
        return self.start + np.stack([self.forward * x, z], axis=-1) * np.asarray(self.scale)

    def angle(self, u: np.ndarray) -> np.ndarray:
        """Bucket angle (T,) rad: Type 1 rises linearly; Type 2 stays then rises sharply near
        the end; Type 3 rises about linearly, more steeply near the end."""
        u = np.clip(np.asarray(u, dtype=float), 0, 1)
        profile = {"Type 1": u, "Type 2": u**4, "Type 3": 0.6 * u + 0.4 * u**3, BACKHOE: u}[self.label]
        return self.angle0 + (self.angle1 - self.angle0) * profile


def dig_shape(label: str, toe: float, slope: float, reach: float, rng: np.random.Generator | _Middle) -> DigShape:
    """A dig of class `label` into a pile whose toe is `toe` m from the swing axis with a
    face at `slope` rad, sized by the machine's `reach` (m, boom + arm + bucket)."""
    deg = np.radians
    if label == "Type 1":  # base of the pile, significantly negative angle, long floor push
        start = np.array([toe - rng.uniform(0.09, 0.11) * reach, 0.03 * reach])
        return DigShape(label, start, rng.uniform(0.14, 0.17) * reach, 0.14 * reach, slope,
                        rng.uniform(0.21, 0.25) * reach, deg(rng.uniform(-35, -25)), deg(rng.uniform(30, 40)))
    if label == "Type 2":  # base of the pile, angle near zero, curving up quickly
        start = np.array([toe - rng.uniform(0.05, 0.07) * reach, 0.04 * reach])
        return DigShape(label, start, rng.uniform(0.08, 0.1) * reach, 0.06 * reach, slope,
                        rng.uniform(0.26, 0.3) * reach, deg(rng.uniform(-4, 4)), deg(rng.uniform(40, 50)))
    if label == "Type 3":  # midway up the face, angle near zero, straight along the face
        height = rng.uniform(0.24, 0.28) * reach
        start = np.array([toe + height / np.tan(slope) + 0.02 * reach, height])
        return DigShape(label, start, 0.0, 0.0, slope, rng.uniform(0.24, 0.28) * reach,
                        deg(rng.uniform(-4, 4)), deg(rng.uniform(35, 45)))
    if label == BACKHOE:  # out beyond the toe, at or a little below the floor, teeth down
        start = np.array([toe + rng.uniform(0.06, 0.12) * reach, -rng.uniform(0.0, 0.04) * reach])
        return DigShape(label, start, rng.uniform(0.1, 0.13) * reach, 0.06 * reach, np.radians(60.0),
                        rng.uniform(0.05, 0.08) * reach, deg(rng.uniform(-75, -60)), deg(rng.uniform(-15, 0)),
                        forward=-1.0)
    raise ValueError(f"unknown dig class {label!r}; one of {CLASSES + (BACKHOE,)}")


class _Middle:
    """Stands in for a random generator: every uniform draw is its range's middle."""

    @staticmethod
    def uniform(low: float, high: float) -> float:
        return 0.5 * (low + high)


def nominal_shape(label: str, toe: float, slope: float, reach: float) -> DigShape:
    """The class's general shape: `dig_shape` with every drawn size at its range's middle."""
    return dig_shape(label, toe, slope, reach, _Middle())


def _even(xz: np.ndarray, n: int) -> np.ndarray:
    """A path (T, 2) resampled at `n` points of even arc length."""
    step = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xz, axis=0).T))])
    u, keep = np.unique(step / max(step[-1], 1e-12), return_index=True)
    even = np.linspace(0.0, 1.0, n)
    return np.column_stack([np.interp(even, u, xz[keep, d]) for d in range(2)])


def stretch(dig: DigShape, reference: DigShape, n: int = 128, iterations: int = 6) -> tuple[float, float]:
    """The stretch (sx, sz) of `reference`'s path about its start that best matches `dig`'s
    (scale included), point by point at even arc length (least squares): how much larger
    than its class's general shape a dig is along and across."""
    fine = np.linspace(0.0, 1.0, 4 * n)
    path = _even(dig.tip(fine) - dig.start, n)
    shape = reference.tip(fine) - reference.start
    scale = np.ones(2)
    for _ in range(iterations):
        q = _even(shape * scale, n) / scale
        scale = (path * q).sum(axis=0) / np.maximum((q * q).sum(axis=0), 1e-12)
    return float(scale[0]), float(scale[1])


@dataclass(frozen=True)
class Redirection:
    """An operator's correction during a dig: a lift `dz` (m) and bucket-angle change
    `dangle` (rad) around progress `at`, over a half-width `width`; temporary (a pulse that
    returns) or kept (a step to the end of the dig)."""

    at: float
    width: float
    dz: float
    dangle: float
    kept: bool

    def weight(self, tau: np.ndarray) -> np.ndarray:
        x = (np.asarray(tau) - self.at) / self.width
        if self.kept:
            return min_jerk((x + 1.0) / 2.0)
        return np.where(np.abs(x) < 1.0, 0.5 * (1.0 + np.cos(np.pi * np.clip(x, -1, 1))), 0.0)
