"""Reference trajectories for the joint, sampled over the MPC horizon.

Each reference is small immutable data, built from a dict (what arrives over Zenoh) with
validation that names the field at fault.
"""

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numba.extending import register_jitable

from model.parameters import Limits

REFERENCE_MARGIN = 0.5  # rad a reference may reach beyond the limits (the barriers stop it)


KIND_SINUSOID = 0.0
KIND_SETPOINT = 1.0


@register_jitable
def reference_at(packed: np.ndarray, t):
    """(q*, qd*) at time(s) t for a packed reference [kind, a, b, c]; one source for numpy
    callers (arrays of t) and the compiled MPC tick (scalars)."""
    if packed[0] == KIND_SINUSOID:
        w = 2.0 * np.pi * packed[3]
        return packed[1] + packed[2] * np.cos(w * t), -packed[2] * w * np.sin(w * t)
    return packed[1] + 0.0 * t, 0.0 * t


class ReferenceError(ValueError):
    """A reference that is malformed or cannot be followed safely."""


@dataclass(frozen=True)
class Sinusoid:
    """q*(t) = center + amplitude cos(2 pi f t): starts at its top, as the paper's Fig. 5-6.

    Defaults: a swing from -0.4 rad down to -2.5 rad, i.e. 0.15 rad past the -2.35 rad limit
    as in the paper's Fig. 5 (amplitude and period are not readable there: assumed).
    """

    center: float = -1.45
    amplitude: float = 1.05
    frequency: float = 0.2

    def packed(self) -> np.ndarray:
        return np.array([KIND_SINUSOID, self.center, self.amplitude, self.frequency])

    def span(self) -> tuple[float, float]:
        return self.center - abs(self.amplitude), self.center + abs(self.amplitude)


@dataclass(frozen=True)
class Setpoint:
    """Hold one position."""

    position: float

    def packed(self) -> np.ndarray:
        return np.array([KIND_SETPOINT, self.position, 0.0, 0.0])

    def span(self) -> tuple[float, float]:
        return self.position, self.position


Reference = Sinusoid | Setpoint
_KINDS = {"sinusoid": Sinusoid, "setpoint": Setpoint}


def reference_from_dict(spec: dict, limits: Limits) -> Reference:
    """Build and check a reference; ReferenceError names the field and the accepted range."""
    if not isinstance(spec, dict):
        raise ReferenceError("reference must be a JSON object with a 'kind'")
    kind = spec.get("kind")
    cls = _KINDS.get(kind) if isinstance(kind, str) else None  # a list is not a kind
    if cls is None:
        raise ReferenceError(f"reference kind {repr(kind)[:40]}: expected one of "
                             f"{', '.join(_KINDS)}")
    fields = set(cls.__dataclass_fields__)
    unknown = set(spec) - fields - {"kind"}
    if unknown:
        raise ReferenceError(f"{kind}: unknown field(s) {', '.join(sorted(unknown))}; "
                             f"expected {', '.join(sorted(fields))}")
    values = {}
    for name in fields & set(spec):
        value = spec[name]
        try:  # an integer beyond a float's range overflows; that is not a number either
            number = float(value) if isinstance(value, int | float) else math.nan
        except OverflowError:
            number = math.inf
        if isinstance(value, bool) or not math.isfinite(number):
            raise ReferenceError(f"{kind}.{name}: expected a finite number, got "
                                 f"{repr(value)[:40]}")
        values[name] = number
    missing = [name for name, f in cls.__dataclass_fields__.items()
               if name not in values and f.default is dataclasses.MISSING]
    if missing:
        raise ReferenceError(f"{kind}: missing field(s) {', '.join(missing)}")
    reference = cls(**values)
    check_reference(reference, limits)
    return reference


def check_reference(reference: Reference, limits: Limits) -> None:
    for name, value in vars(reference).items():
        if not math.isfinite(value):
            raise ReferenceError(f"{type(reference).__name__.lower()}.{name}: expected a finite "
                                 f"number, got {value!r}")
    low, high = reference.span()
    if low < limits.position_min - REFERENCE_MARGIN or high > limits.position_max + \
            REFERENCE_MARGIN:
        raise ReferenceError(
            f"reference spans [{low:.3f}, {high:.3f}] rad; it may reach at most "
            f"{REFERENCE_MARGIN} rad beyond the limits [{limits.position_min}, "
            f"{limits.position_max}] rad")
    if isinstance(reference, Sinusoid):
        peak_velocity = abs(reference.amplitude) * 2.0 * math.pi * abs(reference.frequency)
        if peak_velocity > limits.velocity_max:
            raise ReferenceError(f"sinusoid peak velocity {peak_velocity:.2f} rad/s exceeds "
                                 f"the {limits.velocity_max} rad/s limit")
