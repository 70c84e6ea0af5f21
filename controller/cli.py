"""`actuatord`: the 1 kHz iLQR loop on a CiA 402 drive, telemetry on Zenoh."""

import argparse
import json
import signal
import sys
from pathlib import Path

from controller.loop import ControlLoop, LoopOptions
from controller.mpc import Mpc
from controller.problem import OcpSettings, Weights
from controller.reference import ReferenceError, Sinusoid, reference_from_dict
from controller.requests import RequestHandler
from controller.zenoh_session import add_zenoh_arguments, open_session
from model.effects import with_truth_effects
from model.parameters import ModelFileError, load_model, parse_payload
from protocol import telemetry
from protocol.assignments import parse_assignments
from protocol.bus_spec import BusSpecError, parse_bus_spec
from sim_bus.faults import parse_schedule


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="actuatord",
        description="Run the paper's iLQR (exponential barriers on position, velocity and "
                    "motor torque) as an MPC on a CiA 402 drive and publish telemetry on Zenoh. "
                    "SIGINT/SIGTERM disable the drive and exit 0.")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--bus", default="vcan0",
                       help="bus spec: vcan0, virtual:NAME, udp_multicast:GROUP[:PORT] "
                            "(default: vcan0)")
    where.add_argument("--sim", action="store_true",
                       help="embedded virtual drive in this process (no bus needed)")
    parser.add_argument("--node-id", type=int, default=2)
    parser.add_argument("--model", help="model TOML (default: the packaged paper defaults)")
    parser.add_argument("--payload-mass", type=float, default=0.0, metavar="KG",
                        help="payload known to the controller (and carried by --sim's drive)")
    parser.add_argument("--payload-position", metavar="X,Y", help="payload position (m)")
    parser.add_argument("--lockstep", action="store_true",
                        help="with --sim: run as fast as the virtual drive answers")
    parser.add_argument("--duration", type=float, metavar="S",
                        help="stop after S seconds of drive time")
    parser.add_argument("--period-us", type=int, default=1000, help="control period (us)")
    parser.add_argument("--horizon", type=int, default=OcpSettings.horizon,
                        help="iLQR horizon in steps (default: %(default)s)")
    parser.add_argument("--dt", type=float, default=OcpSettings.dt,
                        help="iLQR step (s, default: %(default)s)")
    parser.add_argument("--weight", action="append", default=[], metavar="NAME=VALUE",
                        help=f"cost weight, one of {', '.join(Weights.__dataclass_fields__)} "
                             "(repeatable)")
    parser.add_argument("--no-current-barrier", action="store_true",
                        help="drop the motor-torque barrier (the paper's Fig. 8 experiment)")
    parser.add_argument("--reference", metavar="JSON",
                        help='reference, e.g. \'{"kind": "setpoint", "position": -1.0}\' '
                             "(default: the paper's sinusoid)")
    parser.add_argument("--prefix", default=telemetry.DEFAULT_PREFIX,
                        help="Zenoh key prefix (default: %(default)s)")
    parser.add_argument("--plot", metavar="DIR", help="save position and current figures here")
    parser.add_argument("--seed", type=int, default=0, help="--sim sensor-noise seed")
    parser.add_argument("--inject-fault", action="append", default=[], metavar="NAME@SECONDS",
                        help="--sim: inject a fault into the virtual drive at that drive time "
                             "(as sim-bus)")
    parser.add_argument("--truth-effect", action="append", default=[], metavar="NAME:K=V,...",
                        help="--sim: hidden effect in the virtual drive's physics (as sim-bus)")
    add_zenoh_arguments(parser)
    return parser


def _usage_error(message: str) -> int:
    print(f"actuatord: error: {message}", file=sys.stderr)
    return 2


def _settings(args: argparse.Namespace) -> OcpSettings:
    weights = parse_assignments(args.weight, Weights.__dataclass_fields__, "--weight")
    if args.no_current_barrier:
        weights["torque_barrier"] = 0.0
    return OcpSettings(horizon=args.horizon, dt=args.dt).with_weights(**weights)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        model = load_model(args.model)
        sim_model = with_truth_effects(model, args.truth_effect)
        schedule = [parse_schedule(text) for text in args.inject_fault]
        if schedule and not args.sim:
            raise ValueError("--inject-fault needs --sim")
        payload = parse_payload(args.payload_mass, args.payload_position)
        if not args.sim:
            parse_bus_spec(args.bus)
        settings = _settings(args)
        reference = (reference_from_dict(json.loads(args.reference), model.limits)
                     if args.reference else Sinusoid())
        if args.lockstep and not args.sim:
            raise ValueError("--lockstep needs --sim (a real drive runs in real time)")
        if not 100 <= args.period_us <= 100_000:
            raise ValueError(f"--period-us {args.period_us}: expected 100..100000")
        if args.duration is not None and not args.duration > 0:
            raise ValueError(f"--duration {args.duration}: expected > 0")
    except (ModelFileError, BusSpecError, ReferenceError, ValueError) as exc:
        return _usage_error(str(exc))

    from driver import DriveError
    from driver.canopen_drive import CanOpenDrive

    period = args.period_us * 1e-6
    sim = None
    bus = args.bus
    if args.sim:
        # the composition root is the one place the controller meets the virtual drive
        from sim_bus.embedded import EmbeddedDrive
        from sim_bus.plant import SensorNoise

        sim = EmbeddedDrive(sim_model, payload, SensorNoise(seed=args.seed), args.node_id)
        for fault, seconds in schedule:
            sim.drive.schedule(fault, seconds)
    try:
        session = open_session(args)
    except ValueError as exc:
        return _usage_error(str(exc))
    from controller.telemetry import TelemetryPublisher

    publisher = TelemetryPublisher(session, args.prefix)
    try:
        # real time: a sample 100 ms late is a dead drive; lock-step: allow for a slow host
        timing = {"period": period, "response_timeout": 1.0 if args.lockstep else 0.1}
        drive = (CanOpenDrive(sim.master_network, args.node_id, **timing) if sim is not None
                 else CanOpenDrive.open(bus, args.node_id, **timing))
    except Exception as exc:
        print(f"actuatord: error: cannot open bus {bus!r}: {exc}", file=sys.stderr)
        publisher.close()
        session.close()
        if sim is not None:
            sim.close()
        return 1
    mpc = Mpc(model, settings, payload, reference)
    loop = ControlLoop(drive, mpc, LoopOptions(period=period, lockstep=args.lockstep,
                                               duration=args.duration,
                                               keep_history=bool(args.plot)),
                       [publisher.publish], lambda: publisher.dropped)
    requests = RequestHandler(loop, mpc, model, payload, publisher.publish_audit)
    publisher.serve_json(telemetry.PARAMETERS, requests.parameters)
    publisher.serve_json(telemetry.REFERENCE, requests.set_reference)
    publisher.serve_json(telemetry.WEIGHTS, requests.set_weights)
    signal.signal(signal.SIGINT, lambda *_: loop.stop())
    signal.signal(signal.SIGTERM, lambda *_: loop.stop())
    try:
        drive.start()
        print(f"actuatord: node {args.node_id} on {'--sim' if args.sim else bus} enabled; "
              f"telemetry under {args.prefix}/", flush=True)
        report = loop.run()
    except DriveError as exc:
        loop.fault(0.0, "drive", str(exc), "drive disabled")
        print(f"actuatord: error: {exc}", file=sys.stderr)
        report = loop.report
        report.exit_code, report.reason = 1, str(exc)
    finally:
        drive.close()
        publisher.close()
        session.close()
        if sim is not None:
            sim.close()
    print(f"actuatord: {report.summary()}", flush=True)
    if args.plot and report.history.get("t"):
        from controller.plots import save_figures

        title = "with current barrier" if not args.no_current_barrier else "no current barrier"
        if payload.mass:
            title = f"{payload.mass:g} kg payload, {title}"
        for path in save_figures(report.history, model.limits, Path(args.plot), title):
            print(f"actuatord: wrote {path}", flush=True)
    return report.exit_code


if __name__ == "__main__":
    sys.exit(main())
