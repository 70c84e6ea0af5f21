"""The virtual drive's options (`--seed`, `--truth-effect`, `--inject-fault`): the hidden
truth and the scheduled faults a virtual drive carries, whether embedded (`--sim`) or served by
`sim-bus`."""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterable
from dataclasses import replace

import numpy as np

from commands.model_options import peak_joint_torque
from commands.parsing import seed
from model.dynamics import inverse_dynamics
from model.effects import EFFECT_KEYS, EFFECT_NAMES
from model.parameters import ActuatorModel, ActuatorParameters
from sim_bus.faults import Fault


def add_virtual_drive_arguments(parser: argparse.ArgumentParser, faults: bool = True,
                                prefix: str = "--sim: ") -> None:
    """The virtual drive's own options: noise seed, hidden effects and, with `faults`,
    scheduled faults. `prefix` marks them as applying to `--sim` only."""

    parser.add_argument("--seed", type=seed, default=0,
                        help=f"{prefix}sensor-noise seed, >= 0 (default: 0)")
    parser.add_argument("--truth-effect", action="append", default=[], metavar="NAME:K=V,...",
                        help=f"{prefix}hidden effect in the virtual drive's physics, e.g. "
                             "stribeck:breakaway_friction=1.5,velocity=0.05 (repeatable; "
                             f"effects: {', '.join(EFFECT_NAMES)})")
    if faults:
        parser.add_argument("--inject-fault", action="append", default=[],
                            metavar="NAME@SECONDS",
                            help=f"{prefix}inject a fault at that drive time (repeatable): "
                                 + ", ".join(f.name.lower() for f in Fault if f is not Fault.NONE)
                                 + "; at run time, write its code to SDO 0x2010")


def fault_schedule(args: argparse.Namespace) -> list[tuple[Fault, float]]:
    """Every `--inject-fault NAME@SECONDS`; ValueError names the one at fault."""
    return [parse_fault(text) for text in args.inject_fault]


def parse_fault(text: str) -> tuple[Fault, float]:
    """'encoder_glitch@2.5' -> (Fault.ENCODER_GLITCH, 2.5 s of drive time)."""
    name, sep, when = text.partition("@")
    try:
        fault = Fault[name.upper()]
    except KeyError:
        names = ", ".join(f.name.lower() for f in Fault if f is not Fault.NONE)
        raise ValueError(f"--inject-fault {text}: fault {name!r}: expected one of "
                         f"{names}") from None
    try:
        seconds = float(when) if sep else 0.0
    except ValueError:
        raise ValueError(f"--inject-fault {text}: {when!r} is not a time in seconds") from None
    if fault is Fault.NONE or not (math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"--inject-fault {text}: expected NAME@SECONDS with a finite time "
                         ">= 0")
    return fault, seconds


def parse_joint_fault(text: str, joints: Iterable[str]) -> tuple[str, Fault, float]:
    """`--inject-fault JOINT:NAME@SECONDS` with --robot: 'arm_left_4_joint:overcurrent_trip@2'
    -> (joint, fault, s of drive time); ValueError names the option and what was expected."""
    joint, sep, fault_text = text.rpartition(":")
    names = list(joints)
    if not sep or joint not in names:
        raise ValueError(f"--inject-fault {text}: with --robot expected JOINT:NAME@SECONDS, "
                         f"JOINT one of {', '.join(names)}")
    fault, seconds = parse_fault(fault_text)
    return joint, fault, seconds


def parse_effect_option(text: str) -> tuple[str, dict[str, float]]:
    """'stribeck:breakaway_friction=1.5,velocity=0.05' -> ('stribeck', {...})."""

    name, _, rest = text.partition(":")
    if name not in EFFECT_KEYS:
        raise ValueError(f"--truth-effect {text}: effect {name!r}: expected one of "
                         f"{', '.join(EFFECT_NAMES)}")
    table = {}
    for item in filter(None, rest.split(",")):
        key, sep, value = item.partition("=")
        if not sep or key not in EFFECT_KEYS[name]:
            raise ValueError(f"--truth-effect {text}: {item!r}: expected KEY=VALUE with KEY "
                             f"one of {', '.join(EFFECT_KEYS[name])}")
        try:
            table[key] = float(value)
        except ValueError:
            raise ValueError(f"--truth-effect {text}: {name}.{key}: {value!r} is not a "
                             "number") from None
    return name, table


def with_truth_effects(model: ActuatorModel, options: Iterable[str]) -> ActuatorModel:
    """The model with the `--truth-effect NAME:KEY=VALUE,...` effects added: the hidden "truth"
    a virtual drive can carry. ValueError names the option at fault."""

    parameters = model.parameters
    peak = peak_joint_torque(model)
    for option in options:
        name, table = parse_effect_option(option)
        for key, value in table.items():
            if EFFECT_KEYS[name][key][1] == "N.m" and not abs(value) <= peak:
                raise ValueError(f"--truth-effect {option}: {key} {value:g} N.m; expected at "
                                 f"most the drive's peak torque {peak:g} N.m")
        try:
            with_it = parameters.with_effect(name, {**parameters.effects.section(name),
                                                    **table})
        except (KeyError, ValueError) as exc:
            raise ValueError(f"--truth-effect {option}: {exc}") from None
        extra = _largest_effect_torque(model, parameters, with_it)
        if not extra <= peak:
            raise ValueError(f"--truth-effect {option}: adds up to {extra:.3g} N.m over the "
                             f"joint's range and velocities; expected at most the drive's peak "
                             f"torque {peak:g} N.m")
        parameters = with_it
    return replace(model, parameters=parameters)


def _largest_effect_torque(model: ActuatorModel, without: ActuatorParameters,
                           with_it: ActuatorParameters) -> float:
    """N.m: the most an effect changes the motor torque over the joint's position range and
    velocities (both directions), from the model's own inverse dynamics. Whatever its keys'
    units (a load coefficient of 1e300 is as absurd as 1e300 N.m), an effect the drive could
    never overcome is not a plausible hidden truth; the physics would overflow too."""
    limits = model.limits
    q, qd = np.meshgrid(np.linspace(limits.position_min, limits.position_max, 41),
                        limits.velocity_max * np.array([-1.0, -0.1, -0.01, 0.01, 0.1, 1.0]))
    q, qd = q.ravel(), qd.ravel()
    direction, qdd = np.sign(qd), np.zeros_like(q)
    with np.errstate(all="ignore"):
        before, _ = inverse_dynamics(q, qd, qdd, direction, without.packed())
        after, _ = inverse_dynamics(q, qd, qdd, direction, with_it.packed())
        largest = float(np.max(np.abs(after - before)))
    return largest if math.isfinite(largest) else math.inf
