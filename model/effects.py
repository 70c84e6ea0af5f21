"""The library of effects the paper's model leaves out, each a physical model with its own
parameters. They live in the dynamics (`model.dynamics`), so the virtual drive, the
identification and the controller's iLQR all use the same equations.

All three act in the transmission (harmonic drive), on the motor side of the torque sensor:
    stribeck                 dry friction rising to a breakaway value near zero velocity:
                             F = Fs + breakaway_friction exp(-(qd / velocity)^2)
    position_ripple          torque periodic in joint angle (harmonic-drive ripple, cogging):
                             amplitude sin(2 pi spatial_frequency q + phase)
    load_dependent_friction  dry friction growing with the transmitted (gravity) load:
                             F = Fs + coefficient |g (MY sin q + MX cos q)|
"""

import math
from dataclasses import dataclass, fields

# TOML section -> {key: (Effects field, unit)}
EFFECT_KEYS = {
    "stribeck": {"breakaway_friction": ("stribeck_breakaway", "N.m"),
                 "velocity": ("stribeck_velocity", "rad/s")},
    "position_ripple": {"amplitude": ("ripple_amplitude", "N.m"),
                        "spatial_frequency": ("ripple_frequency", "cycles/rad"),
                        "phase": ("ripple_phase", "rad")},
    "load_dependent_friction": {"coefficient": ("load_friction", "N.m per N.m of load")},
}
EFFECT_NAMES = tuple(EFFECT_KEYS)


@dataclass(frozen=True)
class Effects:
    stribeck_breakaway: float = 0.0
    stribeck_velocity: float = 0.05
    ripple_amplitude: float = 0.0
    ripple_frequency: float = 0.0
    ripple_phase: float = 0.0
    load_friction: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            if not math.isfinite(getattr(self, f.name)):
                raise ValueError(f"effect parameter {f.name} must be finite")
        if self.stribeck_velocity <= 0:
            raise ValueError("stribeck velocity must be > 0")

    def enabled(self) -> list[str]:
        out = []
        if self.stribeck_breakaway != 0.0:
            out.append("stribeck")
        if self.ripple_amplitude != 0.0:
            out.append("position_ripple")
        if self.load_friction != 0.0:
            out.append("load_dependent_friction")
        return out

    def section(self, name: str) -> dict[str, float]:
        """The TOML table of one effect."""
        return {key: getattr(self, field) for key, (field, _) in EFFECT_KEYS[name].items()}


def effects_from_tables(tables: dict[str, dict[str, float]]) -> Effects:
    """Effects from {section: {key: value}}; KeyError/ValueError name what is wrong."""
    values = {}
    for name, table in tables.items():
        if name not in EFFECT_KEYS:
            raise KeyError(f"unknown effect {name!r}; expected one of {', '.join(EFFECT_NAMES)}")
        for key, value in table.items():
            if key not in EFFECT_KEYS[name]:
                raise KeyError(f"{name}.{key}: unknown key; expected "
                               f"{', '.join(EFFECT_KEYS[name])}")
            values[EFFECT_KEYS[name][key][0]] = float(value)
    return Effects(**values)
