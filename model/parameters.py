"""Actuator parameters loaded from a model TOML file, with provenance and strict validation.

A model file is input that people edit by hand, so every error names the file and the field.
"""

import math
import tomllib
from dataclasses import dataclass, field, fields, replace
from importlib.resources import files
from pathlib import Path

import numpy as np

from model import dynamics
from model.effects import EFFECTS, LIBRARY_NAMES, Effects, effects_from_tables

GRAVITY = 9.81  # m/s^2, standard gravity as used in the paper's g (MY sin q + MX cos q)


class ModelFileError(ValueError):
    """A model TOML that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class ActuatorParameters:
    """Joint-level parameters of the paper's model (SI). Friction and offsets are split into the
    motor side and the joint (link) side, because the torque sensor only sees the link side."""

    drive_gain: float
    torque_sensor_gain: float
    first_moment_x: float
    first_moment_y: float
    link_inertia: float
    motor_inertia: float
    viscous_friction_motor: float
    viscous_friction_joint: float
    dry_friction_motor: float
    dry_friction_joint: float
    torque_offset_motor: float
    torque_offset_joint: float
    effects: Effects = Effects()

    @property
    def inertia(self) -> float:
        return self.link_inertia + self.motor_inertia

    @property
    def viscous_friction(self) -> float:
        return self.viscous_friction_motor + self.viscous_friction_joint

    @property
    def dry_friction(self) -> float:
        return self.dry_friction_motor + self.dry_friction_joint

    @property
    def torque_offset(self) -> float:
        return self.torque_offset_motor + self.torque_offset_joint

    def with_payload(self, payload: "Payload") -> "ActuatorParameters":
        """A point mass on the link adds (m x, m y) to the first moments and m (x^2 + y^2) to
        the link inertia (paper, section II)."""
        return replace(
            self,
            first_moment_x=self.first_moment_x + payload.mass * payload.x,
            first_moment_y=self.first_moment_y + payload.mass * payload.y,
            link_inertia=self.link_inertia + payload.mass * (payload.x**2 + payload.y**2),
        )

    def packed(self) -> np.ndarray:
        """The flat vector the compiled dynamics take (layout in model.dynamics)."""
        p = np.zeros(dynamics.N_PARAMS)
        p[dynamics.P_DRIVE_GAIN] = self.drive_gain
        p[dynamics.P_INERTIA] = self.inertia
        p[dynamics.P_GRAVITY_MX] = GRAVITY * self.first_moment_x
        p[dynamics.P_GRAVITY_MY] = GRAVITY * self.first_moment_y
        p[dynamics.P_VISCOUS] = self.viscous_friction
        p[dynamics.P_DRY] = self.dry_friction
        p[dynamics.P_OFFSET] = self.torque_offset
        for name, table in self.effects.tables().items():
            block = EFFECTS[name].pack(table)
            start = dynamics.EFFECT_OFFSET[name]
            p[start:start + len(block)] = block
        p[dynamics.P_LINK_INERTIA] = self.link_inertia
        p[dynamics.P_VISCOUS_JOINT] = self.viscous_friction_joint
        p[dynamics.P_DRY_JOINT] = self.dry_friction_joint
        p[dynamics.P_OFFSET_JOINT] = self.torque_offset_joint
        return p

    def with_effect(self, name: str, table: dict[str, float]) -> "ActuatorParameters":
        """These parameters with one effect set (others kept)."""
        return replace(self, effects=self.effects.with_table(name, table))


# an actuator's SI parameters and limits lie far within these magnitudes; beyond them the
# dynamics, the drive's integer units and the solver over- or underflow (K_j = 1e-300 made a
# joint torque reading no PDO holds), so a file outside them is a mistake, not a robot
MAGNITUDE_MAX = 1e6
POSITIVE_MIN = 1e-6


@dataclass(frozen=True)
class Payload:
    mass: float = 0.0
    x: float = 0.0
    y: float = 0.0

    def __post_init__(self) -> None:
        for name in ("mass", "x", "y"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise ValueError(f"payload {name} must be finite")
            if abs(value) > MAGNITUDE_MAX:  # m (x^2 + y^2) would overflow past ~1e154
                raise ValueError(f"payload {name} {value:g}: expected at most "
                                 f"{MAGNITUDE_MAX:g} in size (kg, m)")
        if self.mass < 0:
            raise ValueError(f"payload mass must be >= 0 kg, got {self.mass}")


@dataclass(frozen=True)
class Limits:
    position_min: float
    position_max: float
    velocity_max: float
    current_max: float


@dataclass(frozen=True)
class ActuatorModel:
    """Parameters, limits and where each number comes from."""

    parameters: ActuatorParameters
    limits: Limits
    provenance: dict[str, str] = field(default_factory=dict)
    std: dict[str, float] = field(default_factory=dict)
    name: str = ""
    source: str = ""


_POSITIVE = {"drive_gain", "torque_sensor_gain", "link_inertia", "motor_inertia"}
_NON_NEGATIVE = {"viscous_friction_motor", "viscous_friction_joint", "dry_friction_motor",
                 "dry_friction_joint"}


def default_model_path() -> Path:
    return Path(str(files("model") / "elbow_default.toml"))


def load_model(path: str | Path | None = None) -> ActuatorModel:
    """Read and validate a model TOML; raises ModelFileError naming the file and the field."""
    path = Path(path) if path is not None else default_model_path()
    try:
        with open(path, "rb") as fh:
            doc = tomllib.load(fh)
    except FileNotFoundError:
        raise ModelFileError(f"{path}: model file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ModelFileError(f"{path}: not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:
        raise ModelFileError(f"{path}: not UTF-8 text (byte {exc.start}); expected a TOML "
                             "model file") from None
    except RecursionError:
        raise ModelFileError(f"{path}: nested too deeply for a model file") from None
    except IsADirectoryError:
        raise ModelFileError(f"{path}: is a directory; expected a TOML model file") from None
    except OSError as exc:
        raise ModelFileError(f"{path}: cannot read: {exc.strerror}") from None

    known_tables = {"meta", "parameters", "provenance", "std", "limits", "limits_provenance",
                    "effects"}
    for table in doc:
        if table not in known_tables:
            raise ModelFileError(f"{path}: unknown table [{table}]; expected one of "
                                 f"{', '.join(sorted(known_tables))}")
    param_names = [f.name for f in fields(ActuatorParameters) if f.name != "effects"]
    values = _numbers(path, doc, "parameters", param_names)
    for name in _POSITIVE:
        if values[name] <= 0:
            raise ModelFileError(f"{path}: [parameters].{name}: expected > 0, got {values[name]}")
        if values[name] < POSITIVE_MIN:
            raise ModelFileError(f"{path}: [parameters].{name}: {values[name]:g}; expected at "
                                 f"least {POSITIVE_MIN:g} (SI units)")
    for name in _NON_NEGATIVE:
        if values[name] < 0:
            raise ModelFileError(f"{path}: [parameters].{name}: expected >= 0, got {values[name]}")
    limit_names = [f.name for f in fields(Limits)]
    limit_values = _numbers(path, doc, "limits", limit_names)
    limits = Limits(**limit_values)
    if not limits.position_min < limits.position_max:
        raise ModelFileError(f"{path}: [limits]: position_min must be below position_max")
    if limits.velocity_max <= 0 or limits.current_max <= 0:
        raise ModelFileError(f"{path}: [limits]: velocity_max and current_max must be > 0")
    # an offset the drive's peak torque cannot balance leaves no current that holds the joint
    peak = values["drive_gain"] * limits.current_max
    for name in ("torque_offset_motor", "torque_offset_joint"):
        if not abs(values[name]) <= peak:
            raise ModelFileError(f"{path}: [parameters].{name}: {values[name]:g} N.m; expected "
                                 f"at most the drive's peak torque drive_gain x current_max = "
                                 f"{peak:g} N.m in size")
    for table, numbers in (("parameters", values), ("limits", limit_values)):
        for name, value in numbers.items():
            if abs(value) > MAGNITUDE_MAX:
                raise ModelFileError(f"{path}: [{table}].{name}: {value:g}; expected at most "
                                     f"{MAGNITUDE_MAX:g} in size (SI units)")

    provenance = _strings(path, doc, "provenance", param_names, required=True)
    provenance.update({f"limits.{k}": v for k, v in
                       _strings(path, doc, "limits_provenance", limit_names, False).items()})
    std = _numbers(path, doc, "std", param_names, required=False)
    effects, effect_provenance = _effects(path, doc)
    provenance.update(effect_provenance)
    meta = doc.get("meta", {})
    return ActuatorModel(parameters=ActuatorParameters(**values, effects=effects), limits=limits,
                         provenance=provenance, std=std, name=str(meta.get("name", "")),
                         source=str(path))


def _effects(path: Path, doc: dict) -> tuple[Effects, dict[str, str]]:
    """[effects.NAME] tables: numbers per the effect's keys plus a `provenance` string."""
    section = _table(path, doc, "effects", required=False)
    tables, provenance = {}, {}
    for name, table in section.items():
        if name not in LIBRARY_NAMES or not isinstance(table, dict):
            raise ModelFileError(f"{path}: [effects.{name}]: unknown effect; expected one of "
                                 f"{', '.join(LIBRARY_NAMES)}")
        table = dict(table)
        note = table.pop("provenance", None)
        if not isinstance(note, str) or not note.strip():
            raise ModelFileError(f"{path}: [effects.{name}].provenance: expected a provenance "
                                 "string")
        provenance[f"effects.{name}"] = note
        tables[name] = _numbers(path, {f"effects.{name}": table}, f"effects.{name}",
                                [key.name for key in EFFECTS[name].keys], required=True)
    try:
        return effects_from_tables(tables), provenance
    except ValueError as exc:
        raise ModelFileError(f"{path}: [effects]: {exc}") from None


def _table(path: Path, doc: dict, table: str, required: bool) -> dict:
    section = doc.get(table)
    if section is None:
        if required:
            raise ModelFileError(f"{path}: missing table [{table}]")
        return {}
    if not isinstance(section, dict):
        raise ModelFileError(f"{path}: [{table}] must be a table")
    return section


def _check_keys(path: Path, table: str, section: dict, names: list[str], required: bool) -> None:
    for key in section:
        if key not in names:
            raise ModelFileError(f"{path}: [{table}].{key}: unknown key; expected one of "
                                 f"{', '.join(names)}")
    if required:
        for name in names:
            if name not in section:
                raise ModelFileError(f"{path}: [{table}].{name}: missing")


def _numbers(path: Path, doc: dict, table: str, names: list[str],
             required: bool = True) -> dict[str, float]:
    section = _table(path, doc, table, required)
    _check_keys(path, table, section, names, required)
    out = {}
    for key, value in section.items():
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ModelFileError(f"{path}: [{table}].{key}: expected a finite number, "
                                 f"got {value!r}")
        try:
            number = float(value)
        except OverflowError:  # TOML integers are unbounded; printing one may be too
            raise ModelFileError(f"{path}: [{table}].{key}: expected a finite number, got an "
                                 "integer too large for a float") from None
        if not math.isfinite(number):
            raise ModelFileError(f"{path}: [{table}].{key}: expected a finite number, "
                                 f"got {value!r}")
        out[key] = number
    return out


def _strings(path: Path, doc: dict, table: str, names: list[str],
             required: bool) -> dict[str, str]:
    section = _table(path, doc, table, required)
    _check_keys(path, table, section, names, required)
    for key, value in section.items():
        if not isinstance(value, str) or not value.strip():
            raise ModelFileError(f"{path}: [{table}].{key}: expected a provenance string")
    return dict(section)
