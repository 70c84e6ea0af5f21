"""The paper's exciting trajectory: back and forth over the joint's whole range with double
S-curve moves whose acceleration, cruise and deceleration phases last equally long, the cruise
velocity raised step by step to a maximum (section III-A, Fig. 3a)."""

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True)
class ExcitingTrajectory:
    position_low: float = -2.2  # rad: 0.15 rad inside the elbow's -2.35 limit (assumed margin)
    position_high: float = -0.15  # rad: 0.15 rad inside the 0 rad limit
    velocity_min: float = 0.4  # rad/s, first cruise velocity (assumed)
    velocity_max: float = 2.4  # rad/s, last cruise velocity (assumed, half the 5 rad/s limit)
    steps: int = 5  # cruise velocities from min to max
    pause: float = 0.2  # s at rest at each end: the data sees stiction and breakaway too

    def __post_init__(self) -> None:
        if not self.position_low < self.position_high:
            raise ValueError("position_low must be below position_high")
        if not 0 < self.velocity_min <= self.velocity_max:
            raise ValueError("need 0 < velocity_min <= velocity_max")
        if self.steps < 1 or self.pause < 0:
            raise ValueError("need steps >= 1 and pause >= 0")

    # the moves and the duration are worked out once (the trajectory is frozen): `sample`
    # runs every cycle, and a linspace per cycle was a fifth of a lock-step recording's loop
    @cached_property
    def moves(self) -> tuple[tuple[float, float, float], ...]:
        """(start, end, cruise velocity) of each move: down then up at each velocity."""
        out = []
        for v in np.linspace(self.velocity_min, self.velocity_max, self.steps):
            out.append((self.position_high, self.position_low, float(v)))
            out.append((self.position_low, self.position_high, float(v)))
        return tuple(out)

    @cached_property
    def duration(self) -> float:
        distance = self.position_high - self.position_low
        return sum(3.0 * distance / (2.0 * v) + self.pause for _, _, v in self.moves)

    def sample(self, t: float) -> tuple[float, float, float]:
        """(q*, qd*, qdd*) at time t (holds the final position after the end)."""
        for start, end, v in self.moves:
            distance = abs(end - start)
            phase = distance / (2.0 * v)  # each of the three phases: D = 2 v T
            sign = 1.0 if end > start else -1.0
            if t < self.pause:
                return start, 0.0, 0.0
            t -= self.pause
            if t < 3.0 * phase:
                travelled, velocity, acceleration = _double_s(t, phase, v)
                return start + sign * travelled, sign * velocity, sign * acceleration
            t -= 3.0 * phase
        return self.position_high, 0.0, 0.0


def _double_s(t: float, phase: float, v: float) -> tuple[float, float, float]:
    """Distance, velocity, acceleration of one move: velocity rises as (1 - cos)/2 (smooth
    acceleration, bounded jerk), cruises, and falls symmetrically; each phase lasts `phase`."""
    w = math.pi / phase
    if t < phase:
        return (0.5 * v * (t - math.sin(w * t) / w), 0.5 * v * (1.0 - math.cos(w * t)),
                0.5 * v * w * math.sin(w * t))
    if t < 2.0 * phase:
        return 0.5 * v * phase + v * (t - phase), v, 0.0
    u = t - 2.0 * phase
    return (1.5 * v * phase + v * u - 0.5 * v * (u - math.sin(w * u) / w),
            v - 0.5 * v * (1.0 - math.cos(w * u)), -0.5 * v * w * math.sin(w * u))


@dataclass(frozen=True)
class SlowSinusoid:
    """q* = center + amplitude sin(2 pi f t): slow, so the joint spends long stretches near
    zero velocity at each turn (where Stribeck friction shows). Values assumed."""

    center: float = -1.2
    amplitude: float = 0.9
    frequency: float = 0.1
    duration: float = 20.0

    def sample(self, t: float) -> tuple[float, float, float]:
        w = 2.0 * math.pi * self.frequency
        return (self.center + self.amplitude * math.sin(w * t),
                self.amplitude * w * math.cos(w * t), -self.amplitude * w * w * math.sin(w * t))
