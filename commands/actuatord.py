"""`actuatord`: the 1 kHz iLQR loop on a CiA 402 drive, telemetry on Zenoh."""

import argparse
import json
import signal
import sys
from pathlib import Path

from commands.options import (
    DriveOpenError,
    add_bus_arguments,
    add_model_argument,
    add_payload_arguments,
    add_virtual_drive_arguments,
    add_zenoh_arguments,
    check_drive_arguments,
    fault_schedule,
    open_drive,
    open_session,
    parse_assignments,
    payload_from_args,
    usage_error,
    with_truth_effects,
)
from controller.loop import ControlLoop, LoopOptions
from controller.mpc import Mpc
from controller.problem import OcpSettings, Weights
from controller.reference import ReferenceError, Sinusoid, reference_from_dict
from controller.requests import RequestHandler
from model.parameters import ModelFileError, load_model
from protocol import telemetry
from protocol.bus_spec import BusSpecError

PROG = "actuatord"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Run the paper's iLQR (exponential barriers on position, velocity and "
                    "motor torque) as an MPC on a CiA 402 drive and publish telemetry on Zenoh. "
                    "SIGINT/SIGTERM disable the drive and exit 0.")
    add_bus_arguments(parser)
    add_model_argument(parser)
    add_payload_arguments(parser, mass_help="payload known to the controller (and carried by "
                                            "--sim's drive, kg)")
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
    add_virtual_drive_arguments(parser)
    add_zenoh_arguments(parser)
    return parser


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
        schedule = fault_schedule(args)
        if schedule and not args.sim:
            raise ValueError("--inject-fault needs --sim")
        payload = payload_from_args(args)
        check_drive_arguments(args)
        settings = _settings(args)
        reference = (reference_from_dict(json.loads(args.reference), model.limits)
                     if args.reference else Sinusoid())
        if not 100 <= args.period_us <= 100_000:
            raise ValueError(f"--period-us {args.period_us}: expected 100..100000")
        if args.duration is not None and not args.duration > 0:
            raise ValueError(f"--duration {args.duration}: expected > 0")
    except (ModelFileError, BusSpecError, ReferenceError, ValueError) as exc:
        return usage_error(PROG, str(exc))

    from driver import DriveError

    period = args.period_us * 1e-6
    try:
        session = open_session(args)
    except ValueError as exc:
        return usage_error(PROG, str(exc))
    from controller.telemetry import TelemetryPublisher

    publisher = TelemetryPublisher(session, args.prefix)
    mpc = Mpc(model, settings, payload, reference)
    loop = ControlLoop(None, mpc, LoopOptions(period=period, lockstep=args.lockstep,
                                              duration=args.duration,
                                              keep_history=bool(args.plot)),
                       publisher.publish, lambda: publisher.dropped)
    requests = RequestHandler(loop, mpc, model, payload, publisher.publish_audit)
    publisher.serve_json(telemetry.PARAMETERS, requests.parameters)
    publisher.serve_json(telemetry.REFERENCE, requests.set_reference)
    publisher.serve_json(telemetry.WEIGHTS, requests.set_weights)
    signal.signal(signal.SIGINT, lambda *_: loop.stop())
    signal.signal(signal.SIGTERM, lambda *_: loop.stop())
    try:
        # real time: a sample 100 ms late is a dead drive; lock-step: allow for a slow host
        drive, sim = open_drive(args, model, sim_model, payload, schedule, period=period,
                                response_timeout=1.0 if args.lockstep else 0.1)
    except DriveOpenError as exc:
        publisher.close()
        session.close()
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 1
    loop.drive = drive
    try:
        drive.start()
        print(f"actuatord: node {args.node_id} on {'--sim' if args.sim else args.bus} enabled; "
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
