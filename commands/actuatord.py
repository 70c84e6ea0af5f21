"""`actuatord`: the 1 kHz iLQR loop on a CiA 402 drive, telemetry on Zenoh."""

import argparse
import json
import signal
import sys
from pathlib import Path

from commands.options import (
    CommandParser,
    DriveOpenError,
    add_bus_arguments,
    add_logging_argument,
    add_model_argument,
    add_payload_arguments,
    add_virtual_drive_arguments,
    add_zenoh_arguments,
    check_drive_arguments,
    check_key_expr,
    check_output_folder,
    check_payload,
    configure_logging,
    fault_schedule,
    int_range,
    job_error,
    open_drive,
    open_session,
    parse_assignments,
    payload_from_args,
    positive_float,
    usage_error,
    with_truth_effects,
)
from controller.loop import ControlLoop, LoopOptions
from controller.mpc import Mpc
from controller.problem import OcpSettings, Weights
from controller.reference import ReferenceError, Sinusoid, reference_from_dict
from controller.requests import RequestHandler
from model.parameters import ActuatorModel, ModelFileError, load_model
from protocol import telemetry
from protocol.bus_spec import BusSpecError

PROG = "actuatord"
# The tick grows linearly with the horizon (bench: 17 us median at 100 steps on this 2-core
# machine), so 1000 steps take about a fifth of a 1 ms period: more cannot keep the rhythm.
MAX_HORIZON = 1000


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(
        prog=PROG,
        description="Run the paper's iLQR (exponential barriers on position, velocity and "
                    "motor torque) as an MPC on a CiA 402 drive and publish telemetry on Zenoh. "
                    "SIGINT/SIGTERM disable the drive and exit 0.")
    add_bus_arguments(parser)
    add_model_argument(parser)
    add_payload_arguments(parser, mass_help="payload known to the controller (and carried by "
                                            "--sim's drive, kg)")
    parser.add_argument("--duration", type=positive_float, metavar="S",
                        help="stop after S seconds of drive time")
    parser.add_argument("--period-us", type=int_range(100, 100_000), default=1000,
                        help="control period (us, default: %(default)s)")
    parser.add_argument("--horizon", type=int, default=OcpSettings.horizon,
                        help=f"iLQR horizon in steps, 2..{MAX_HORIZON} "
                             "(default: %(default)s)")
    parser.add_argument("--dt", type=positive_float, default=OcpSettings.dt,
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
    add_logging_argument(parser)
    return parser


def _settings(args: argparse.Namespace, model: ActuatorModel) -> OcpSettings:
    if not 2 <= args.horizon <= MAX_HORIZON:
        raise ValueError(f"--horizon {args.horizon}: expected 2..{MAX_HORIZON} steps (the tick "
                         "grows with the horizon and must fit in the control period)")
    weights = parse_assignments(args.weight, Weights.__dataclass_fields__, "--weight")
    if args.no_current_barrier:
        weights["torque_barrier"] = 0.0
    try:
        settings = OcpSettings(horizon=args.horizon, dt=args.dt).with_weights(**weights)
    except ValueError as exc:
        raise ValueError(f"--weight/--dt: {exc}") from None
    _check_resolution(settings, model, args.period_us)
    return settings


def _check_resolution(settings: OcpSettings, model: ActuatorModel, period_us: int) -> None:
    """Refuse a step the controller cannot keep safe: at the velocity limit, one iLQR step or
    one control period may move the joint at most half the position barrier's width 1/alpha
    (over which the barrier grows by e), so the wall is felt at least two steps before it. A
    coarser plan hops over the limit without the cost seeing it; a longer period leaves the
    joint that far unwatched. At the defaults (1/alpha = 0.1 rad, 5 rad/s) 100 ms and 20 ms
    steps drove the joint through the drive's position window (EMCY 0x8612); 10 ms held."""
    alpha, velocity = settings.sharpness.position, model.limits.velocity_max
    longest = 0.5 / (alpha * velocity)  # s
    for option, step, shown in (("--dt", settings.dt, f"{settings.dt:g} s"),
                                ("--period-us", period_us * 1e-6, f"{period_us} us")):
        if step > longest:
            raise ValueError(
                f"{option} {shown}: at the velocity limit {velocity:g} rad/s the joint moves "
                f"{velocity * step:.3g} rad per step, more than half the position barrier's "
                f"width 1/alpha = {1 / alpha:g} rad; expected at most {longest * 1e3:g} ms")


def _reference(text: str | None, model: ActuatorModel):
    if text is None:
        return Sinusoid()
    try:
        spec = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise ValueError(f"--reference {text[:40]!r}: expected a JSON object ({exc})") from None
    return reference_from_dict(spec, model.limits)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(PROG, args.log_level)
    try:
        model = load_model(args.model)
        sim_model = with_truth_effects(model, args.truth_effect)
        schedule = fault_schedule(args)
        if schedule and not args.sim:
            raise ValueError("--inject-fault needs --sim")
        payload = payload_from_args(args)
        check_payload(model, payload)
        check_drive_arguments(args)
        check_key_expr("--prefix", args.prefix, wildcards=False)
        settings = _settings(args, model)
        reference = _reference(args.reference, model)
        if args.plot:
            check_output_folder("--plot", args.plot)
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
    try:
        # real time: a sample 100 ms late is a dead drive; lock-step: allow for a slow host
        connection = open_drive(args, model, sim_model, payload, schedule, period=period,
                                response_timeout=1.0 if args.lockstep else 0.1)
    except DriveOpenError as exc:
        publisher.close()
        session.close()
        return job_error(PROG, str(exc))
    drive = connection.drive
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
        print(f"actuatord: node {args.node_id} on {connection.where} enabled; "
              f"telemetry under {args.prefix}/", flush=True)
        report = loop.run()
    except DriveError as exc:
        loop.fault(0.0, "drive", str(exc), "drive disabled")
        job_error(PROG, str(exc))
        report = loop.report
        report.exit_code, report.reason = 1, str(exc)
    finally:
        connection.close()
        publisher.close()
        session.close()
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
