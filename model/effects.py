"""The effect registry: what the paper's joint model leaves out, one object per effect.

Each effect declares everything the rest of the project needs to know about it, so that no
other module names an effect or repeats its formula:
  * its TOML keys with units and defaults (the `[effects.NAME]` table of a model file) and
    what makes a table valid at all;
  * its torque term, compiled (numba `register_jitable`) into the forward dynamics, the iLQR
    and the inverse dynamics alike (`model.dynamics` chains the terms of every effect);
  * its regressor columns (the term at unit coefficients, so they cannot disagree with it) and
    the grid of its nonlinear "shape" parameter that model-gap scans;
  * how fitted coefficients map back to its TOML keys;
  * its plausibility constraints: a fit that needs to break them is not that effect.

An effect acts on one side of the model, and neither side is seen by the joint torque sensor:
  * in the transmission (harmonic drive), on the motor side of the sensor. Its term returns
    its share of the dry-friction level (the magnitude that multiplies sign(qd), bounded by
    the set-valued friction in the integrator) and of the torque the drive must overcome,
    each with its partial derivatives:
        (level, d level/dq, d level/dqd, torque, d torque/dq, d torque/dqd)
    from the effect's own block of the packed parameters, p[k:k + slots], and the base
    model's Coulomb level and gravity torque (with its derivative), which some effects scale;
  * in the drive: the torque a current makes. Its term returns the current it loses and the
    slope of that loss, (loss, d loss/di), so the motor makes drive_gain x (i - loss(i)): a
    torque constant that is not constant.
Some effects change over a recording (`time_dependent`): their block carries the value at
the moment, set from the time since the start (`at_elapsed`) by whoever has a clock (the
virtual drive, model-gap on a recording's rows).
Each effect also says what kind of recording reveals it (`reveals`): model-gap quotes it when
two effects explain the same residual, and the README lists it.

`LIBRARY` is what model files may carry and what model-gap searches. `HIDDEN_ONLY` holds
physics the virtual drive can be given as a hidden truth (`--truth-effect`) to test what
model-gap says about an effect outside its library; model-gap never proposes it and model
files refuse it.
"""

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numba.extending import register_jitable

LOAD_SMOOTHING = 0.05  # N.m: |G| ~ sqrt(G^2 + 0.05^2) keeps the derivative finite at G = 0
MIN_RIPPLE_PERIODS = 2.0  # over the travelled range: fewer is a slow position trend, no ripple


@dataclass(frozen=True)
class Key:
    """One number of an effect's TOML table."""

    name: str
    unit: str
    default: float
    meaning: str


@dataclass(frozen=True)
class FitContext:
    """What the plausibility constraints of a fitted effect are judged against."""

    coulomb: float  # N.m, the refitted Coulomb level
    position_range: float  # rad travelled in the data
    current_peak: float = math.inf  # A, the largest |current| in the data


@dataclass(frozen=True)
class Regressors:
    """The rows an effect's regressor columns are computed from (arrays, one value a row)."""

    q: np.ndarray
    qd: np.ndarray
    direction: np.ndarray  # the dry friction's direction (filtered sign(qd))
    current: np.ndarray  # A, measured
    elapsed: np.ndarray  # s since the start of the row's recording
    gravity: np.ndarray  # N.m, the model's gravity torque (payload included)
    d_gravity: np.ndarray  # its slope in q
    coulomb: float  # N.m, the model's Coulomb level
    drive_gain: float  # N.m/A


class Effect:
    """Base of every effect; subclasses fill in the class attributes and the methods."""

    name: str = ""
    model: str = ""  # the formula, for people
    keys: tuple[Key, ...] = ()
    strength: str = ""  # the key whose zero switches the effect off
    slots: int = 0  # numbers in the packed parameter vector
    shape: str | None = None  # the key model-gap scans (nonlinear parameter), if any
    shape_grid: np.ndarray = np.zeros(1)
    coefficients: int = 1  # linear coefficients of the regressor at a given shape
    side: str = "transmission"  # or "drive" (see the module docstring)
    time_dependent: bool = False  # its block holds a value that changes with elapsed time
    reveals: str = ""  # the kind of recording that shows it

    @staticmethod
    def term(q, qd, p, k, coulomb, gravity, d_gravity):
        """A transmission effect's share (see the module docstring)."""
        raise NotImplementedError

    @staticmethod
    def current_term(current, p, k):
        """A drive-side effect's current loss and its slope (see the module docstring)."""
        raise NotImplementedError

    def grid(self, rows: Regressors) -> np.ndarray:
        """The shapes model-gap scans on these rows (a fixed grid unless the effect's shape
        scales with the data)."""
        return self.shape_grid

    def at_elapsed(self, block: np.ndarray, elapsed: float) -> None:
        """Set a time-dependent block (a view into the packed parameters) to its value
        `elapsed` seconds after the start."""

    def validate(self, table: Mapping[str, float]) -> None:
        """ValueError when the physics is undefined with these numbers (beyond finiteness)."""

    def pack(self, table: Mapping[str, float]) -> tuple[float, ...]:
        raise NotImplementedError

    def packed_fit(self, shape: float, coefficients: Sequence[float]) -> tuple[float, ...]:
        """The packed block for a fit: shape and linear coefficients."""
        raise NotImplementedError

    def table_from_fit(self, shape: float, coefficients: Sequence[float]) -> dict[str, float]:
        raise NotImplementedError

    def violations(self, table: Mapping[str, float], context: FitContext) -> list[str]:
        """Why a fitted table is not physically this effect (empty: plausible)."""
        return []

    @property
    def units(self) -> dict[str, str]:
        return {key.name: key.unit for key in self.keys}

    def defaults(self) -> dict[str, float]:
        return {key.name: key.default for key in self.keys}

    def columns(self, rows: Regressors, shape: float) -> np.ndarray:
        """Regressor columns at this shape, one per linear coefficient: the term evaluated at
        unit coefficients (the dry-friction part times the sliding direction). They are the
        effect's share of drive_gain x current minus the torque the model needs without it."""
        out = []
        for j in range(self.coefficients):
            unit = np.zeros(self.coefficients)
            unit[j] = 1.0
            block = np.array(self.packed_fit(shape, unit))
            level, _, _, torque, _, _ = self.term(rows.q, rows.qd, block, 0, rows.coulomb,
                                                  rows.gravity, rows.d_gravity)
            out.append(level * rows.direction + torque)
        return np.column_stack(out)


# --- compiled terms (each reads its own block p[k:k + slots]) -------------------------------

@register_jitable
def _stribeck_term(q, qd, p, k, coulomb, gravity, d_gravity):
    zero = 0.0 * qd
    if p[k] == 0.0:
        return zero, zero, zero, zero, zero, zero
    vs = p[k + 1]
    bump = p[k] * np.exp(-(qd / vs) ** 2)
    return bump, zero, -2.0 * qd / (vs * vs) * bump, zero, zero, zero


@register_jitable
def _harmonic(q, p, k):
    """a sin(wq) + b cos(wq) with (a, b, w) = p[k:k + 3], and its slope in q (free when
    a = b = 0)."""
    if p[k] == 0.0 and p[k + 1] == 0.0:
        return 0.0 * q, 0.0 * q
    w = p[k + 2]
    s, c = np.sin(w * q), np.cos(w * q)
    return p[k] * s + p[k + 1] * c, w * (p[k] * c - p[k + 1] * s)


@register_jitable
def _position_ripple_term(q, qd, p, k, coulomb, gravity, d_gravity):
    torque, slope = _harmonic(q, p, k)
    zero = 0.0 * q
    return zero, zero, zero, torque, slope, zero


@register_jitable
def _load_friction_term(q, qd, p, k, coulomb, gravity, d_gravity):
    zero = 0.0 * q
    if p[k] == 0.0:
        return zero, zero, zero, zero, zero, zero
    smooth_abs = np.sqrt(gravity * gravity + LOAD_SMOOTHING**2)
    return p[k] * smooth_abs, p[k] * gravity * d_gravity / smooth_abs, zero, zero, zero, zero


@register_jitable
def _friction_ripple_term(q, qd, p, k, coulomb, gravity, d_gravity):
    level, slope = _harmonic(q, p, k)
    zero = 0.0 * q
    return level, slope, zero, zero, zero, zero


@register_jitable
def _smooth_reversal_term(q, qd, p, k, coulomb, gravity, d_gravity):
    zero = 0.0 * qd
    if p[k] == 0.0:
        return zero, zero, zero, zero, zero, zero
    th = np.tanh(qd / p[k])
    # level Fs |tanh(qd / v)| instead of Fs: the effect's share is -Fs (1 - |tanh|)
    return (-coulomb * (1.0 - np.abs(th)), zero, coulomb * np.sign(qd) * (1.0 - th * th) / p[k],
            zero, zero, zero)


@register_jitable
def _saturation_loss(current, p, k):
    """The current lost to saturation, c sign(i) max(|i| - i_k, 0)^2, and its slope in i."""
    if p[k] == 0.0:
        return 0.0 * current, 0.0 * current
    excess = np.maximum(np.abs(current) - p[k + 1], 0.0)
    return p[k] * np.sign(current) * excess * excess, 2.0 * p[k] * excess


@register_jitable
def _warm_up_term(q, qd, p, k, coulomb, gravity, d_gravity):
    # the level at the moment (p[k + 2], set by `at_elapsed`), whatever the motion
    zero = 0.0 * q + 0.0 * qd
    return p[k + 2] + zero, zero, zero, zero, zero, zero


# --- the effects ------------------------------------------------------------------------------

class Stribeck(Effect):
    name = "stribeck"
    model = "dry friction rising to a breakaway value near zero speed: Fs + E exp(-(qd/vs)^2)"
    keys = (Key("breakaway_friction", "N.m", 0.0, "E: breakaway minus Coulomb friction"),
            Key("velocity", "rad/s", 0.05, "vs: the Stribeck velocity"))
    strength = "breakaway_friction"
    reveals = ("slow passes and reversals (|qd| below a few tenths of rad/s): the friction rises "
               "towards zero speed, whatever the load or angle")
    slots = 2
    shape = "velocity"
    shape_grid = np.geomspace(0.005, 0.5, 30)
    term = staticmethod(_stribeck_term)

    def validate(self, table):
        if table["velocity"] <= 0:
            raise ValueError("stribeck velocity must be > 0")

    def pack(self, table):
        return table["breakaway_friction"], table["velocity"]

    def packed_fit(self, shape, coefficients):
        return coefficients[0], shape

    def table_from_fit(self, shape, coefficients):
        return {"breakaway_friction": float(coefficients[0]), "velocity": float(shape)}

    def violations(self, table, context):
        if table["breakaway_friction"] <= 0:
            return [f"breakaway friction {table['breakaway_friction']:.3f} N.m is not above the "
                    "Coulomb level (friction that falls toward zero speed is not Stribeck "
                    "friction)"]
        return []


class PositionRipple(Effect):
    name = "position_ripple"
    model = "torque periodic in angle (harmonic drive, cogging): A sin(2 pi f q + phi)"
    keys = (Key("amplitude", "N.m", 0.0, "A"),
            Key("spatial_frequency", "cycles/rad", 0.0, "f, found from the data"),
            Key("phase", "rad", 0.0, "phi"))
    strength = "amplitude"
    reveals = ("motion over the whole travel in both directions: a torque periodic in angle with "
               "the same sign whichever way the joint moves")
    slots = 3
    shape = "spatial_frequency"
    shape_grid = np.arange(1.0, 40.0, 0.2)  # refined between neighbours by model-gap
    coefficients = 2  # a sin(wq) + b cos(wq)
    term = staticmethod(_position_ripple_term)

    def validate(self, table):
        if table["amplitude"] < 0 or table["spatial_frequency"] < 0:
            raise ValueError(f"{self.name} amplitude and spatial_frequency must be >= 0")

    def pack(self, table):
        amplitude, phase = table["amplitude"], table["phase"]
        return (amplitude * math.cos(phase), amplitude * math.sin(phase),
                2.0 * math.pi * table["spatial_frequency"])

    def packed_fit(self, shape, coefficients):
        return coefficients[0], coefficients[1], 2.0 * math.pi * shape

    def table_from_fit(self, shape, coefficients):
        a, b = coefficients  # a sin(wq) + b cos(wq) = A sin(wq + phase)
        return {"amplitude": float(math.hypot(a, b)), "spatial_frequency": float(shape),
                "phase": float(math.atan2(b, a))}

    def violations(self, table, context):
        periods = table["spatial_frequency"] * context.position_range
        if periods < MIN_RIPPLE_PERIODS:
            return [f"{periods:.1f} periods over the {context.position_range:.2f} rad travelled "
                    f"(a ripple needs {MIN_RIPPLE_PERIODS:g} or more)"]
        return []


class _OneNumber(Effect):
    """An effect whose one key is its one packed slot and its one linear coefficient."""

    slots = 1

    def pack(self, table):
        return (table[self.strength],)

    def packed_fit(self, shape, coefficients):
        return (coefficients[0],)

    def table_from_fit(self, shape, coefficients):
        return {self.strength: float(coefficients[0])}


class LoadDependentFriction(_OneNumber):
    name = "load_dependent_friction"
    model = "dry friction growing with the transmitted gravity load: Fs + mu |G(q)|"
    keys = (Key("coefficient", "N.m per N.m of load", 0.0, "mu"),)
    strength = "coefficient"
    reveals = ("motion at high gravity load both lifting and lowering: the extra friction "
               "opposes the motion, so it adds current when lifting and takes it away when "
               "lowering (braking)")
    term = staticmethod(_load_friction_term)

    def violations(self, table, context):
        mu = table["coefficient"]
        if not 0 < mu < 1:
            return [f"load coefficient {mu:.3f} is outside (0, 1): friction must grow with the "
                    "load and stay below it"]
        return []


class FrictionRipple(PositionRipple):
    name = "friction_ripple"
    model = ("dry friction periodic in angle (wave-generator meshing): "
             "Fs + A sin(2 pi f q + phi)")
    reveals = ("motion over the whole travel in both directions: a torque periodic in angle "
               "that reverses with the direction of motion")
    term = staticmethod(_friction_ripple_term)

    def violations(self, table, context):
        out = super().violations(table, context)
        if table["amplitude"] >= context.coulomb:
            out.append(f"amplitude {table['amplitude']:.3f} N.m is not below the Coulomb level "
                       f"{context.coulomb:.3f} N.m (dry friction would change sign with angle)")
        return out


class SmoothReversal(_OneNumber):
    """Outside the library on purpose (see the module docstring)."""

    name = "smooth_reversal"
    model = "dry friction reversing smoothly instead of sticking: Fs tanh(qd / v)"
    keys = (Key("velocity", "rad/s", 0.0, "v: the speed over which the friction reverses"),)
    strength = "velocity"
    reveals = "slow reversals, and creeping under a push below the Coulomb level"
    term = staticmethod(_smooth_reversal_term)

    def validate(self, table):
        if table["velocity"] < 0:
            raise ValueError("smooth_reversal velocity must be >= 0")


class TorqueConstantSaturation(Effect):
    """Magnetic saturation of the motor: above a knee current each ampere makes less torque.
    The knee is scanned as a fraction of the largest current in the data, so the same search
    serves a joint of any size."""

    name = "torque_constant_saturation"
    model = ("torque per ampere falling above a knee current (magnetic saturation): "
             "drive_gain (i - c sign(i) max(|i| - i_k, 0)^2)")
    keys = (Key("coefficient", "1/A", 0.0, "c: current lost per A^2 beyond the knee"),
            Key("knee_current", "A", 0.0, "i_k: where the torque constant starts to fall"))
    strength = "coefficient"
    side = "drive"
    reveals = ("high currents in both directions of power flow, lifting and lowering (braking) "
               "a heavy load: each ampere makes less torque whatever the motion")
    slots = 2
    shape = "knee_current"
    shape_grid = np.linspace(0.0, 0.9, 19)  # fractions of the largest |current| in the data
    current_term = staticmethod(_saturation_loss)

    def grid(self, rows):
        return self.shape_grid * float(np.max(np.abs(rows.current)))

    def validate(self, table):
        if table["knee_current"] < 0:
            raise ValueError(f"{self.name} knee_current must be >= 0")

    def pack(self, table):
        return table["coefficient"], table["knee_current"]

    def packed_fit(self, shape, coefficients):
        return coefficients[0], shape

    def table_from_fit(self, shape, coefficients):
        return {"coefficient": float(coefficients[0]), "knee_current": float(shape)}

    def columns(self, rows, shape):
        loss, _ = _saturation_loss(rows.current, np.array([1.0, shape]), 0)
        return (rows.drive_gain * loss)[:, None]

    def violations(self, table, context):
        c, knee = table["coefficient"], table["knee_current"]
        if c <= 0:
            return [f"coefficient {c:.4g} 1/A is not > 0 (a torque constant that grows with "
                    "the current is not saturation)"]
        slope = 1.0 - 2.0 * c * max(context.current_peak - knee, 0.0)
        if slope <= 0:
            return [f"coefficient {c:.4g} 1/A beyond {knee:.3g} A makes the torque fall with "
                    f"the current before the data's peak {context.current_peak:.3g} A"]
        return []


class WarmUpFriction(Effect):
    """Outside the library (see the module docstring): the virtual drive carries it so that
    tests can check what model-gap says about friction that drifts over a recording."""

    name = "warm_up_friction"
    model = ("dry friction above its warm value at the start, decaying as the gear warms: "
             "Fs + W exp(-t / tau), t the time since the start")
    keys = (Key("excess_friction", "N.m", 0.0, "W: dry friction above the warm value at t = 0"),
            Key("time_constant", "s", 30.0, "tau: the decay's time constant"))
    strength = "excess_friction"
    time_dependent = True
    reveals = ("a recording started cold and long against the time constant: friction above its "
               "warm value, decaying with the time since the start")
    slots = 3  # W, tau, and W exp(-t / tau) at the moment
    term = staticmethod(_warm_up_term)

    def validate(self, table):
        if table["time_constant"] <= 0:
            raise ValueError(f"{self.name} time_constant must be > 0")

    def pack(self, table):
        return table["excess_friction"], table["time_constant"], table["excess_friction"]

    def at_elapsed(self, block, elapsed):
        block[2] = block[0] * math.exp(-elapsed / block[1])


LIBRARY: tuple[Effect, ...] = (Stribeck(), PositionRipple(), LoadDependentFriction(),
                               FrictionRipple(), TorqueConstantSaturation())
HIDDEN_ONLY: tuple[Effect, ...] = (SmoothReversal(), WarmUpFriction())
PHYSICS: tuple[Effect, ...] = LIBRARY + HIDDEN_ONLY  # what the dynamics carry, in packed order
EFFECTS: dict[str, Effect] = {effect.name: effect for effect in PHYSICS}
LIBRARY_NAMES = tuple(effect.name for effect in LIBRARY)
# what `--truth-effect` accepts: {effect: {key: (key, unit)}}
EFFECT_KEYS = {effect.name: {key.name: (key.name, key.unit) for key in effect.keys}
               for effect in PHYSICS}
EFFECT_NAMES = tuple(EFFECT_KEYS)
TRANSMISSION = tuple(effect for effect in PHYSICS if effect.side == "transmission")
DRIVE = tuple(effect for effect in PHYSICS if effect.side == "drive")
TIME_DEPENDENT = tuple(effect for effect in PHYSICS if effect.time_dependent)


class Effects:
    """The effects a model carries: a full table per enabled effect, in registry order.
    Immutable and comparable; tables whose strength is zero are dropped (switched off)."""

    __slots__ = ("_tables",)

    def __init__(self, tables: Mapping[str, Mapping[str, float]] | None = None):
        tables = tables or {}
        for name in tables:
            if name not in EFFECTS:
                raise KeyError(f"unknown effect {name!r}; expected one of "
                               f"{', '.join(EFFECT_NAMES)}")
        stored = []
        for effect in PHYSICS:
            if effect.name not in tables:
                continue
            table = effect.defaults()
            for key, value in tables[effect.name].items():
                if key not in table:
                    raise KeyError(f"{effect.name}.{key}: unknown key; expected "
                                   f"{', '.join(table)}")
                value = float(value)
                if not math.isfinite(value):
                    raise ValueError(f"effect parameter {effect.name}.{key} must be finite")
                table[key] = value
            effect.validate(table)
            if table[effect.strength] != 0.0:
                stored.append((effect.name, tuple(table.items())))
        self._tables = tuple(stored)

    def enabled(self) -> list[str]:
        return [name for name, _ in self._tables]

    def section(self, name: str) -> dict[str, float]:
        """The TOML table of one effect (its defaults when it is not enabled)."""
        for stored, items in self._tables:
            if stored == name:
                return dict(items)
        return EFFECTS[name].defaults()

    def tables(self) -> dict[str, dict[str, float]]:
        return {name: dict(items) for name, items in self._tables}

    def with_table(self, name: str, table: Mapping[str, float]) -> "Effects":
        return Effects({**self.tables(), name: table})

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Effects) and self._tables == other._tables

    def __hash__(self) -> int:
        return hash(self._tables)

    def __repr__(self) -> str:
        return f"Effects({self.tables()!r})"


def effects_from_tables(tables: dict[str, dict[str, float]]) -> Effects:
    """Effects from {section: {key: value}}; KeyError/ValueError name what is wrong."""
    return Effects(tables)
