"""What the commands share: the drive options (`--bus`/`--sim`/`--node-id`/`--lockstep` and the
virtual drive's `--seed`, `--truth-effect`, `--inject-fault`), the one place a master drive is
opened, the payload and `NAME=VALUE` options, the Zenoh session options (spelled like Zenoh's
own tools: `--listen`, `--connect`, `--zenoh-config`, `--no-multicast-scouting`) and the one
way a usage error is reported.

Command-line text is parsed here and nowhere below: the library layers take typed values and
raise typed errors; a command turns those into one line on stderr and exit code 2.
"""

import argparse
import json
import sys
from collections.abc import Iterable
from dataclasses import replace

import zenoh

from model.effects import EFFECT_KEYS, EFFECT_NAMES
from model.parameters import ActuatorModel, Payload
from protocol.bus_spec import parse_bus_spec
from sim_bus.faults import Fault


def usage_error(prog: str, message: str) -> int:
    """Bad usage or input: one line on stderr naming the option or file; exit code 2."""
    print(f"{prog}: error: {message}", file=sys.stderr)
    return 2


# --- the drive: a bus, or the virtual drive embedded in this process --------------------------

def add_bus_arguments(parser: argparse.ArgumentParser, sim: bool = True) -> None:
    """`--bus` and `--node-id`; with `sim`, also `--sim` (exclusive with `--bus`) and
    `--lockstep`."""
    bus_help = ("bus spec: vcan0 (SocketCAN), virtual:NAME, udp_multicast:GROUP[:PORT] "
                "(default: vcan0)")
    if sim:
        where = parser.add_mutually_exclusive_group()
        where.add_argument("--bus", default="vcan0", help=bus_help)
        where.add_argument("--sim", action="store_true",
                           help="embedded virtual drive in this process (no bus needed)")
        parser.add_argument("--lockstep", action="store_true",
                            help="with --sim: run as fast as the virtual drive answers")
    else:
        parser.add_argument("--bus", default="vcan0", help=bus_help)
    parser.add_argument("--node-id", type=int, default=2, help="CANopen node id (default: 2)")


def add_virtual_drive_arguments(parser: argparse.ArgumentParser, faults: bool = True,
                                prefix: str = "--sim: ") -> None:
    """The virtual drive's own options: noise seed, hidden effects and, with `faults`,
    scheduled faults. `prefix` marks them as applying to `--sim` only."""
    parser.add_argument("--seed", type=int, default=0,
                        help=f"{prefix}sensor-noise seed (default: 0)")
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


def check_drive_arguments(args: argparse.Namespace) -> None:
    """Refuse a drive choice that cannot work, before anything is opened. Raises BusSpecError
    or ValueError naming the option."""
    sim = getattr(args, "sim", False)
    if not sim:
        parse_bus_spec(args.bus)
    if getattr(args, "lockstep", False) and not sim:
        raise ValueError("--lockstep needs --sim (a real drive runs in real time)")


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
        raise ValueError(f"fault {name!r}: expected one of {names}") from None
    try:
        seconds = float(when) if sep else 0.0
    except ValueError:
        raise ValueError(f"fault {text!r}: {when!r} is not a time in seconds") from None
    if fault is Fault.NONE or seconds < 0:
        raise ValueError(f"fault {text!r}: need a fault and a time >= 0")
    return fault, seconds


class DriveOpenError(Exception):
    """The bus or the drive could not be opened (the job fails: exit code 1)."""


def open_drive(args: argparse.Namespace, model: ActuatorModel, sim_model: ActuatorModel,
               payload: Payload, schedule: Iterable[tuple[Fault, float]] = (), **timing):
    """The master drive for `--bus` or `--sim`, and the embedded virtual drive (None on a bus).

    `model` is what the master knows of the joint (its velocity limit guards the encoder, its
    drive gain converts torque commands); `sim_model` and `payload` are the virtual drive's
    physics (its hidden truth), `schedule` its injected faults; `timing` goes to the master
    (`period`, `response_timeout`). The caller closes the master, then the virtual drive."""
    from driver.canopen_drive import CanOpenDrive

    lockstep = getattr(args, "lockstep", False)
    options = {"lockstep": lockstep, "velocity_limit": model.limits.velocity_max,
               "drive_gain": model.parameters.drive_gain, **timing}
    if not args.sim:
        try:
            return CanOpenDrive.open(args.bus, args.node_id, **options), None
        except Exception as exc:
            raise DriveOpenError(f"cannot open bus {args.bus!r}: {exc}") from exc
    # the composition root is the one place a master meets the virtual drive
    from sim_bus.embedded import EmbeddedDrive
    from sim_bus.plant import SensorNoise

    sim = EmbeddedDrive(sim_model, payload, SensorNoise(seed=args.seed), args.node_id,
                        lockstep=lockstep)
    for fault, seconds in schedule:
        sim.device.schedule(fault, seconds)
    try:
        return CanOpenDrive(sim.master_network, args.node_id, **options), sim
    except Exception as exc:
        sim.close()
        raise DriveOpenError(f"cannot open the embedded drive: {exc}") from exc


# --- the model, the payload and hidden effects -----------------------------------------------

def add_model_argument(parser: argparse.ArgumentParser,
                       help: str = "model TOML (default: the packaged paper defaults)") -> None:
    parser.add_argument("--model", help=help)


def add_payload_arguments(parser: argparse.ArgumentParser, mass_default: float | None = 0.0,
                          mass_help: str = "point mass carried by the link (kg)") -> None:
    parser.add_argument("--payload-mass", type=float, default=mass_default, metavar="KG",
                        help=mass_help)
    parser.add_argument("--payload-position", metavar="X,Y",
                        help="payload position in the link frame (m), e.g. 0,0.05")


def payload_from_args(args: argparse.Namespace) -> Payload:
    return parse_payload(args.payload_mass, args.payload_position)


def parse_payload(mass: float, position: str | None) -> Payload:
    """Payload from `--payload-mass KG` and `--payload-position X,Y` (metres, link frame)."""
    x = y = 0.0
    if position is not None:
        parts = position.split(",")
        try:
            x, y = (float(v) for v in parts)
        except ValueError:
            raise ValueError(f"payload position {position!r}: expected X,Y in metres, "
                             "e.g. 0,0.05") from None
    if mass > 0 and position is None:
        raise ValueError("payload mass given without --payload-position X,Y")
    return Payload(mass=mass, x=x, y=y)


def parse_effect_option(text: str) -> tuple[str, dict[str, float]]:
    """'stribeck:breakaway_friction=1.5,velocity=0.05' -> ('stribeck', {...})."""
    name, _, rest = text.partition(":")
    if name not in EFFECT_KEYS:
        raise ValueError(f"effect {name!r}: expected one of {', '.join(EFFECT_NAMES)}")
    table = {}
    for item in filter(None, rest.split(",")):
        key, sep, value = item.partition("=")
        if not sep or key not in EFFECT_KEYS[name]:
            raise ValueError(f"effect {name}: {item!r}: expected KEY=VALUE with KEY one of "
                             f"{', '.join(EFFECT_KEYS[name])}")
        try:
            table[key] = float(value)
        except ValueError:
            raise ValueError(f"effect {name}.{key}: {value!r} is not a number") from None
    return name, table


def with_truth_effects(model: ActuatorModel, options: Iterable[str]) -> ActuatorModel:
    """The model with the `--truth-effect NAME:KEY=VALUE,...` effects added: the hidden "truth"
    a virtual drive can carry. ValueError names the option at fault."""
    parameters = model.parameters
    for option in options:
        name, table = parse_effect_option(option)
        try:
            parameters = parameters.with_effect(name, {**parameters.effects.section(name),
                                                       **table})
        except (KeyError, ValueError) as exc:
            raise ValueError(f"--truth-effect {option}: {exc}") from None
    return replace(model, parameters=parameters)


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


# --- Zenoh -----------------------------------------------------------------------------------

def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("Zenoh")
    group.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    group.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to connect to (repeatable)")
    group.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config file")
    group.add_argument("--no-multicast-scouting", action="store_true",
                       help="disable multicast scouting (peers only via --connect/--listen)")


def zenoh_config(args: argparse.Namespace) -> zenoh.Config:
    """A Zenoh config from the file (if any) with the command-line options applied on top.
    Raises ValueError naming the option at fault."""
    try:
        config = zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config else (
            zenoh.Config())
    except Exception as exc:  # zenoh raises its own ZError for unreadable or invalid files
        raise ValueError(f"--zenoh-config {args.zenoh_config}: {exc}") from None
    for option, key in (("listen", "listen/endpoints"), ("connect", "connect/endpoints")):
        endpoints = getattr(args, option)
        if endpoints:
            try:
                config.insert_json5(key, json.dumps(endpoints))
            except Exception as exc:
                raise ValueError(f"--{option} {' '.join(endpoints)}: {exc}") from None
    if args.no_multicast_scouting:
        config.insert_json5("scouting/multicast/enabled", "false")
    return config


def open_session(args: argparse.Namespace) -> zenoh.Session:
    config = zenoh_config(args)
    try:
        return zenoh.open(config)
    except Exception as exc:
        raise ValueError(f"cannot open the Zenoh session: {exc}") from None
