"""Dig cycles of a shovel or excavator, planned in the bucket's space and turned into joints.

A session holds still for `hold` seconds (the calibration frame), then runs dig cycles:
lower to the face, dig (one of the three classes of PAPER.md or a backhoe's drag, with
reactive noise, an operator's redirection and proportional or non-proportional scaling;
within the linkage's reach and joint limits, see `fit_in_reach`), lift, swing to the
truck, dump, swing back. The tip (x forward from the swing axis, z above the ground) and
bucket angle are planned in the house's vertical plane, the swing separately; joint values
come from the linkage's closed-form inverse kinematics at any requested times, so every
camera's frames get exact truth. The base may bounce a little (small 6-DoF motion).

Shapes: T times, J joints.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mocap.core.classes import OTHER
from mocap.core.geometry import rpy_to_matrix
from mocap.core.ik import PlanarChain
from mocap.core.machine import Machine
from mocap.errors import InputError
from mocap.synthetic.paths import (BACKHOE, CLASSES, DigShape, Redirection, SmoothNoise, dig_shape, min_jerk,
                                   nominal_shape, stretch)

ADVANCE_CYCLES = 10  # the face advances by 0.8 % of the reach a dig for this many digs, then the machine
# steps forward (its frame is the world's, so the face is back where it began)
SHRINK = np.linspace(1.0, 0.8, 11)  # factors tried on a dig's size, then
SHIFT = np.linspace(0.0, 0.2, 11)  # moves of its start towards the machine, as shares of the reach
REACH_MARGIN = 0.005  # of the boom-arm reach kept in hand: a fully stretched linkage turns its joints fast


@dataclass(frozen=True)
class Pile:
    """The muck pile: its toe `toe` m from the swing axis, face `slope` rad, `height` m,
    centred on `azimuth` rad (world, from x towards y), `width` m along the face."""

    toe: float
    slope: float
    height: float
    azimuth: float
    width: float


@dataclass(frozen=True)
class Truck:
    """Where the bucket dumps: `azimuth` rad, tip `distance` m from the swing axis, bed
    `height` m above the ground."""

    azimuth: float
    distance: float
    height: float


@dataclass(frozen=True)
class Cycle:
    """One dig cycle's truth; times in seconds on the reference clock. `scale` (sx, sz) the
    operator's scaling of this dig's own shape; `stretch` (sx, sz) the dig's size against its
    class's general shape (`paths.stretch`: the scaling and the dig's own push and rise),
    what an analysis can measure and truth/cycles.csv's scale_x, scale_z; `lift` (m) and
    `turn` (rad) the operator's redirection's change of the tip's height and bucket angle
    (0 without one)."""

    index: int
    label: str
    scaling: str
    scale: tuple[float, float]
    redirection: str
    start: float
    dig_start: float
    dig_end: float
    end: float
    stretch: tuple[float, float] = (1.0, 1.0)
    lift: float = 0.0
    turn: float = 0.0


@dataclass(frozen=True)
class _Segment:
    """A piece of the tip plan over [t0, t1]: a minimum-jerk move from `a` to `b`
    (x, z, beta), or a dig."""

    t0: float
    t1: float
    a: np.ndarray
    b: np.ndarray
    dig: DigShape | None = None
    noise: SmoothNoise | None = None
    redirection: Redirection | None = None

    def evaluate(self, t: np.ndarray) -> np.ndarray:
        tau = np.clip((t - self.t0) / (self.t1 - self.t0), 0.0, 1.0)
        if self.dig is None:
            return self.a + (self.b - self.a) * min_jerk(tau)[:, None]
        return dig_state(self.dig, tau, self.noise, self.redirection, t)


def dig_state(dig: DigShape, tau: np.ndarray, noise: SmoothNoise | None, redirection: Redirection | None,
              t: np.ndarray | None = None) -> np.ndarray:
    """(x, z, beta) (T, 3) of a dig at time fraction `tau` (T,); noise vanishes at both ends."""
    u = min_jerk(tau)
    state = np.concatenate([dig.tip(u), dig.angle(u)[:, None]], axis=-1)
    if redirection is not None:
        w = redirection.weight(tau)
        state[:, 1] += redirection.dz * w
        state[:, 2] += redirection.dangle * w
    if noise is not None and t is not None:
        state += noise(t) * np.sin(np.pi * tau)[:, None]
    return state


@dataclass(frozen=True)
class DigMotion:
    """A planned session: tip segments, swing keyframes, base bouncing, cycles, pile, truck."""

    chain: PlanarChain
    segments: tuple[_Segment, ...]
    swing_times: np.ndarray
    swing_values: np.ndarray
    bounce: SmoothNoise | None
    hold: float
    duration: float
    cycles: tuple[Cycle, ...]
    pile: Pile
    truck: Truck

    def tip_plan(self, t: np.ndarray) -> np.ndarray:
        """Planned (x, z, beta) (T, 3): x forward from the swing axis and z above the
        ground (m) in the house's vertical plane, bucket angle (rad)."""
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.duration)
        starts = np.array([s.t0 for s in self.segments])
        which = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(starts) - 1)
        out = np.empty((len(t), 3))
        for k in np.unique(which):
            pick = which == k
            out[pick] = self.segments[k].evaluate(t[pick])
        return out

    def swing(self, t: np.ndarray) -> np.ndarray:
        """Swing angle (T,) rad: minimum-jerk moves between keyframes."""
        t = np.clip(np.asarray(t, dtype=float), self.swing_times[0], self.swing_times[-1])
        k = np.clip(np.searchsorted(self.swing_times, t, side="right") - 1, 0, len(self.swing_times) - 2)
        t0, t1 = self.swing_times[k], self.swing_times[k + 1]
        v0, v1 = self.swing_values[k], self.swing_values[k + 1]
        return v0 + (v1 - v0) * min_jerk((t - t0) / np.maximum(t1 - t0, 1e-12))

    def joints(self, t: np.ndarray) -> np.ndarray:
        """Joint values (T, J) rad / m at times `t` (T,) s."""
        plan = self.tip_plan(t)
        tip = np.stack([plan[:, 0], plan[:, 1] - self.chain.house_height], axis=-1)
        return self.chain.inverse(tip, plan[:, 2], self.swing(t))

    def world_from_base(self, t: np.ndarray) -> np.ndarray:
        """The base's pose (T, 4, 4): identity while holding still, bouncing after."""
        t = np.asarray(t, dtype=float)
        out = np.tile(np.eye(4), (len(t), 1, 1))
        if self.bounce is None:
            return out
        motion = self.bounce(t) * min_jerk(t - self.hold)[:, None]  # ramps up over 1 s
        out[:, :3, :3] = rpy_to_matrix(motion[:, :3])
        out[:, :3, 3] = motion[:, 3:]
        return out


def plan_session(
    machine: Machine,
    n_cycles: int,
    rng: np.random.Generator,
    *,
    classes: tuple[str, ...] = CLASSES,
    redirect_probability: float = 0.4,
    reactive: float = 1.0,
    bounce: float = 1.0,
    hold: float = 2.0,
    end_pause: tuple[float, float] = (0.0, 0.0),
    swing_lead: tuple[float, float] = (0.4, 0.4),
    redirect_at: tuple[float, float] = (0.35, 0.65),
) -> DigMotion:
    """Plan `n_cycles` dig cycles of `machine`; the classes cycle through `classes` in a
    random order (`paths.BACKHOE` plans a backhoe's digs, whose truth class is ``other``);
    `reactive` and `bounce` scale the reactive noise and the base's bouncing
    (0 turns them off). Each dig's bucket rests at the end of the dig for a time drawn from
    `end_pause` (s) before the lift-out; the swing to the truck starts a share drawn from
    `swing_lead` of the lift-out's time after the lift-out starts (below 0: before the dig
    ends, the house turning while the bucket still cuts); a redirection is centred at a
    share of the dig drawn from `redirect_at`. Ranges of zero width draw nothing, so the
    defaults plan the sessions they always did."""
    chain = PlanarChain.from_machine(machine)
    reach = float(np.linalg.norm(chain.offsets, axis=1).sum())
    pace = float(np.clip(np.sqrt(reach / 15.5), 0.6, 1.0))  # small machines cycle faster
    deg = np.radians
    pin_x = float(chain.pin[0])
    pile = Pile(pin_x + 0.6 * reach, deg(rng.uniform(64, 72)), 0.7 * reach, deg(rng.uniform(-5, 5)), 1.4 * reach)
    side = rng.choice([-1.0, 1.0])
    truck = Truck(side * deg(rng.uniform(75, 105)), pin_x + 0.66 * reach, 0.42 * reach)
    carry = np.array([pin_x + 0.62 * reach, 0.55 * reach, deg(45.0)])
    dump = np.array([truck.distance, truck.height + 0.1 * reach, deg(-20.0)])
    labels = [classes[k] for k in np.concatenate([rng.permutation(len(classes)) for _ in range(n_cycles)])][:n_cycles]

    segments: list[_Segment] = []
    swing_t, swing_v = [0.0], [pile.azimuth]
    cycles: list[Cycle] = []
    t, state = hold, carry
    segments.append(_Segment(0.0, hold, carry, carry))
    for i, label in enumerate(labels):
        toe = pile.toe + 0.008 * reach * (i % ADVANCE_CYCLES)  # the face advances; the machine steps after
        dig = dig_shape(label, toe, pile.slope, reach, rng)
        proportional = bool(rng.random() < 0.5)
        if proportional:
            scale = (rng.uniform(0.88, 1.08),) * 2
        else:
            sx = rng.uniform(0.88, 1.05)
            scale = (sx, sx * rng.choice([0.85, 1.15]) * rng.uniform(0.97, 1.03))
        dig = replace(dig, scale=scale)
        redirection = None
        if rng.random() < redirect_probability:
            redirection = Redirection(
                rng.uniform(*redirect_at), rng.uniform(0.08, 0.14), rng.choice([-1, 1]) * rng.uniform(0.015, 0.03) * reach,
                rng.choice([-1, 1]) * deg(rng.uniform(8, 18)), bool(rng.random() < 0.4),
            )
        noise = None
        if reactive > 0:
            noise = SmoothNoise.random(rng, reactive * np.array([0.003 * reach, 0.003 * reach, deg(1.0)]), (0.8, 3.0))
        azimuth = pile.azimuth + deg(rng.uniform(-10, 10))
        t_return, t_dig, t_lift = 5.0 * pace, rng.uniform(6.5, 8.5) * pace, 3.0 * pace
        t_swing, t_dump = rng.uniform(4.5, 5.5) * pace, 5.0 * pace
        start = t
        dig_start = start + t_return + 0.5 * pace
        dig = fit_in_reach(chain, machine.joint_limits, dig, redirection, noise, (dig_start, dig_start + t_dig),
                           state, carry, reach, label=f"dig {i + 1} ({label})", machine_name=machine.name)
        scale = dig.scale
        begin = np.concatenate([dig.start, [dig.angle0]])
        segments.append(_Segment(start, dig_start, state, begin))
        swing_t += [start, start + t_return]
        swing_v += [swing_v[-1], azimuth]
        dig_end = dig_start + t_dig
        segments.append(_Segment(dig_start, dig_end, begin, begin, dig, noise, redirection))
        end_state = dig_state(dig, np.ones(1), None, redirection)[0]
        pause = _draw(rng, end_pause)
        if pause > 0:
            segments.append(_Segment(dig_end, dig_end + pause, end_state, end_state))
        lift_out = dig_end + pause
        lifted = lift_out + t_lift
        segments.append(_Segment(lift_out, lifted, end_state, carry))
        swing_start = lift_out + _draw(rng, swing_lead) * t_lift
        swing_t += [swing_start, swing_start + t_swing]
        swing_v += [azimuth, truck.azimuth]
        at_truck = swing_t[-1]
        segments.append(_Segment(lifted, at_truck, carry, carry))
        tipped = at_truck + 0.5 * t_dump
        segments.append(_Segment(at_truck, tipped, carry, dump))
        end = tipped + 0.5 * t_dump
        segments.append(_Segment(tipped, end, dump, carry))
        cycles.append(Cycle(i, OTHER if label == BACKHOE else label,
                            "proportional" if proportional else "non-proportional",
                            (float(scale[0]), float(scale[1])),
                            "none" if redirection is None else ("kept" if redirection.kept else "temporary"),
                            start, dig_start, dig_end, end, stretch(dig, nominal_shape(label, toe, pile.slope, reach)),
                            *((0.0, 0.0) if redirection is None else (float(redirection.dz), float(redirection.dangle)))))
        t, state = end, carry
    segments.append(_Segment(t, t + 4.0 * pace, state, carry))
    swing_t += [t, t + 4.0 * pace]
    swing_v += [swing_v[-1], pile.azimuth]
    duration = t + 4.0 * pace + 1.0
    segments.append(_Segment(t + 4.0 * pace, duration, carry, carry))
    swing_t.append(duration)
    swing_v.append(pile.azimuth)

    bounce_noise = None
    if bounce > 0:
        sd = bounce * np.array([deg(0.12), deg(0.2), deg(0.04), 0.002, 0.002, 0.006]) * np.sqrt(reach / 15.5)
        bounce_noise = SmoothNoise.random(rng, sd, (1.0, 4.0))
    return DigMotion(chain, tuple(segments), np.array(swing_t), np.array(swing_v), bounce_noise, hold, duration,
                     tuple(cycles), pile, truck)




def _draw(rng: np.random.Generator, span: tuple[float, float]) -> float:
    """A uniform draw from `span`, or its value without a draw when it has no width."""
    return float(span[0]) if span[0] == span[1] else float(rng.uniform(*span))


def fit_in_reach(chain: PlanarChain, limits: np.ndarray, dig: DigShape, redirection: Redirection | None,
                 noise: SmoothNoise | None, span: tuple[float, float], before: np.ndarray, after: np.ndarray,
                 reach: float, *, label: str = "dig", machine_name: str = "machine", samples: int = 200) -> DigShape:
    """`dig` itself when the linkage reaches all of it — the lowering from the state
    `before` (x, z, beta), the dig over the times `span` (s) with its noise and redirection,
    the lift to `after` — inside the joint `limits` (J, 2); else the dig made smaller about
    its start (`SHRINK`, the truth's scale shrinks with it) and then, if need be, started
    nearer the machine (`SHIFT` × `reach` m; a backhoe's drag farther out) too: the first
    that fits. A pile that has advanced beyond the reach over many cycles is dug where the
    machine reaches it.

    Raises InputError when no such dig fits the machine.
    """
    tau = np.linspace(0.0, 1.0, samples)
    blend = min_jerk(tau)[:, None]
    for shift in SHIFT:
        for f in SHRINK:
            trial = dig if shift == 0 and f == 1 else replace(
                dig, start=dig.start - np.array([dig.forward * shift * reach, 0.0]),
                scale=(dig.scale[0] * f, dig.scale[1] * f))
            begin = np.concatenate([trial.start, [trial.angle0]])
            end = dig_state(trial, np.ones(1), None, redirection)[0]
            states = np.concatenate([
                before + (begin - before) * blend,
                dig_state(trial, tau, noise, redirection, span[0] + tau * (span[1] - span[0])),
                end + (after - end) * blend,
            ])
            tip = np.stack([states[:, 0], states[:, 1] - chain.house_height], axis=-1)
            if chain.reachable(tip, states[:, 2], limits, REACH_MARGIN).all():
                return trial
    raise InputError(
        f"{label} does not fit the linkage even {1 - SHRINK[-1]:.0%} smaller and {SHIFT[-1]:.0%} of the reach "
        "moved; its joint limits or proportions do not suit these digs",
        path=machine_name,
    )


def check_limits(machine: Machine, joints: np.ndarray) -> None:
    """Raise ValueError naming the joint and by how much when joints (T, J) leave the
    model's limits."""
    limits = machine.joint_limits
    worst = np.maximum(limits[:, 0] - joints, joints - limits[:, 1]).max(axis=0)
    outside = np.flatnonzero(worst > 1e-9)
    if outside.size:
        j = outside[0]
        raise ValueError(
            f"planned motion leaves the limits of joint {machine.joint_names[j]!r} by "
            f"{np.degrees(worst[j]):.1f} deg; limits {np.degrees(limits[j]).round(1).tolist()}"
        )
