"""The model, the payload and `NAME=VALUE` options (`--model`, `--payload-mass`,
`--payload-position`, `--weight`): parsed and checked against the model before a drive is
touched."""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterable
from typing import TYPE_CHECKING

from commands.file_options import check_input_option
from commands.parsing import non_negative_float
from protocol.input_files import present

# model.parameters (and numba with it) is imported where a model is used, not here: every
# command's parser is built from this module, and `--help` should answer at once
if TYPE_CHECKING:
    from model.parameters import ActuatorModel, Payload


def add_model_argument(parser: argparse.ArgumentParser,
                       help: str = "model TOML (default: the packaged paper defaults)") -> None:
    parser.add_argument("--model", help=help)


def load_model_option(path: str | None, option: str = "--model") -> ActuatorModel:
    """The model a `--model FILE` names (None: the packaged defaults), stat'ed before it is
    read so a device, a FIFO or a huge file is refused at once. ModelFileError or ValueError
    names the file."""
    from model.parameters import load_model

    if path is not None and present(path):  # a missing file: load_model says so
        check_input_option(option, path, "a model TOML")
    return load_model(path)


def add_payload_arguments(parser: argparse.ArgumentParser, mass_default: float | None = 0.0,
                          mass_help: str = "point mass carried by the link (kg)") -> None:
    parser.add_argument("--payload-mass", type=non_negative_float, default=mass_default,
                        metavar="KG", help=mass_help)
    parser.add_argument("--payload-position", metavar="X,Y",
                        help="payload position in the link frame (m), e.g. 0,0.05")


def payload_from_args(args: argparse.Namespace) -> Payload:
    return parse_payload(args.payload_mass, args.payload_position)


def parse_payload(mass: float, position: str | None) -> Payload:
    """Payload from `--payload-mass KG` and `--payload-position X,Y` (metres, link frame)."""
    from model.parameters import Payload

    x = y = 0.0
    if position is not None:
        parts = position.split(",")
        try:
            x, y = (float(v) for v in parts)
        except ValueError:
            x = y = math.nan
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"--payload-position {position!r}: expected X,Y in metres, "
                             "e.g. 0,0.05")
    if mass > 0 and position is None:
        raise ValueError("payload mass given without --payload-position X,Y")
    try:
        return Payload(mass=mass, x=x, y=y)
    except ValueError as exc:
        raise ValueError(f"--payload-mass {mass:g} --payload-position {position}: {exc}") \
            from None


def peak_joint_torque(model: ActuatorModel) -> float:
    """N.m: the most the drive can apply (drive_gain x current_max)."""
    return model.parameters.drive_gain * model.limits.current_max


def check_payload(model: ActuatorModel, payload: Payload) -> None:
    """Refuse a payload the drive could not hold: with it, the arm's gravity torque at its
    worst angle, g |(MX, MY)|, would exceed the drive's peak torque, so no controller keeps the
    joint anywhere but hanging (and absurd values overflow the physics)."""
    from model.parameters import GRAVITY

    loaded = model.parameters.with_payload(payload)
    gravity = GRAVITY * math.hypot(loaded.first_moment_x, loaded.first_moment_y)
    peak = peak_joint_torque(model)
    if not gravity <= peak:
        raise ValueError(f"--payload-mass {payload.mass:g} at --payload-position "
                         f"{payload.x:g},{payload.y:g}: the arm's gravity torque would reach "
                         f"{gravity:.3g} N.m; expected a payload the drive can hold (at most "
                         f"{peak:g} N.m, drive_gain x current_max)")


def parse_assignments(items: Iterable[str], allowed: Iterable[str] | None,
                      what: str) -> dict[str, float]:
    """`NAME=VALUE` items (`--weight position=300`, `dashboard set weights position=300`) as
    {name: float}; ValueError names the item, and the allowed names when there are any."""
    allowed = list(allowed) if allowed is not None else None
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or (allowed is not None and name not in allowed):
            expected = f" with NAME one of {', '.join(allowed)}" if allowed is not None else ""
            raise ValueError(f"{what}: {item!r}: expected NAME=VALUE{expected}")
        try:
            out[name] = float(value)
        except ValueError:
            raise ValueError(f"{what}: {item!r}: {value!r} is not a number") from None
    return out
