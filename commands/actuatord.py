"""`actuatord`: the 1 kHz iLQR loop on a CiA 402 drive, telemetry on Zenoh."""

import argparse
import dataclasses
import json
import signal
import sys
import threading
from collections.abc import Callable
from pathlib import Path

from commands.bus_options import (
    add_bus_arguments,
    add_real_time_argument,
    apply_real_time,
    check_drive_arguments,
    check_eds,
    load_esi_option,
    open_drive,
)
from commands.file_options import check_output_file, check_output_folder
from commands.first_run import CompileNotice
from commands.log_options import (
    ThreadFailures,
    add_logging_argument,
    configure_logging,
    internal_error,
    job_error,
    reports_failures,
)
from commands.model_options import (
    add_model_argument,
    add_payload_arguments,
    check_payload,
    load_model_option,
    parse_assignments,
    payload_from_args,
)
from commands.parsing import CommandParser, int_range, positive_float, usage_error
from commands.ros2_options import add_ros2_argument
from commands.sim_options import add_virtual_drive_arguments, fault_schedule, with_truth_effects
from commands.zenoh_options import (
    add_zenoh_arguments,
    check_key_expr,
    open_session,
    zenoh_config,
)
from controller.loop import QUICK_STOPPED, ControlLoop, LoopOptions
from controller.mpc import BatchMpc, JointProblem
from controller.problem import MAX_HORIZON, OcpSettings, ResolutionError, Weights
from controller.reference import ReferenceError, Sinusoid, check_reference, reference_from_dict
from controller.requests import RequestHandler
from driver import process_image
from model.parameters import ActuatorModel, ModelFileError, Payload
from protocol import telemetry
from protocol.bus_spec import BusSpecError, is_ethercat
from robot.wiring import Connection, DriveOpenError

PROG = "actuatord"


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
    parser.add_argument("--prefix",
                        help=f"Zenoh key prefix (default: {telemetry.DEFAULT_PREFIX}, with "
                             "--robot robots/NAME)")
    parser.add_argument("--robot", metavar="FILE",
                        help="every joint of a robot file (robots/*.toml) in one cycle: one "
                             "SYNC per CAN bus and one frame per EtherCAT line, one batched "
                             "MPC call; --sim embeds every drive (a CAN bus as an in-process "
                             "link, an EtherCAT line as virtual slaves linked to the master's "
                             "process image); --inject-fault then takes "
                             "JOINT:NAME@SECONDS")
    parser.add_argument("--plot", metavar="DIR", help="save position and current figures here")
    parser.add_argument("--report", metavar="FILE",
                        help="write the run's figures as JSON (cycles, missed cycles by cause, "
                             "jitter, MPC tick and the master's own cost in us, exit code)")
    add_virtual_drive_arguments(parser)
    add_real_time_argument(parser)
    add_zenoh_arguments(parser)
    add_ros2_argument(parser)
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
        settings.check_weights()
    except ValueError as exc:
        raise ValueError(f"--weight/--dt: {exc}") from None
    _check_resolution(settings, model, args.period_us)
    return settings


def _check_resolution(settings: OcpSettings, model: ActuatorModel, period_us: int) -> None:
    """OcpSettings.check_resolution, its refusal naming the option."""
    try:
        settings.check_resolution(model.limits.velocity_max, period_us * 1e-6)
    except ResolutionError as exc:
        shown = (f"--dt {settings.dt:g} s" if exc.quantity == "dt"
                 else f"--period-us {period_us} us")
        raise ValueError(f"{shown}: {exc}") from None


def _reference(text: str | None, model: ActuatorModel):
    if text is None:
        return Sinusoid()
    try:
        spec = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise ValueError(f"--reference {text[:40]!r}: expected a JSON object ({exc})") from None
    return reference_from_dict(spec, model.limits)


@reports_failures(PROG)
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(PROG, args.log_level)
    # from before the first thread starts: an exception that ends any thread stops the loop
    # (or keeps it from starting), and the run then ends with every drive quick-stopped
    stop = threading.Event()
    with ThreadFailures(stop.set) as threads:
        setup = _robot_setup(args) if args.robot is not None else _joint_setup(args)
        if isinstance(setup, int):  # bad input: said, with its exit code
            return setup
        return _run(args, setup, stop, threads)


def _write_report(args: argparse.Namespace, report) -> None:
    """--report: the run's figures as JSON, written whole (after the summary, which stays the
    word of record if the file cannot be written)."""
    if args.report is None:
        return
    try:
        Path(args.report).write_text(json.dumps(report.figures(), indent=1) + "\n")
    except OSError as exc:
        job_error(PROG, f"--report {args.report}: cannot write: {exc.strerror or exc}")


@dataclasses.dataclass
class _Setup:
    """A run checked and its controller compiled, from the command line (one joint, a robot of
    one) or a robot file: what opens the drives, and what the one run needs."""

    batch: BatchMpc
    names: list[str]  # the joints, in the robot's order
    models: list[ActuatorModel]  # what the controller knows of each joint
    payloads: list[Payload]  # what each joint carries, as the controller knows it
    period: float  # s
    open: Callable[[], Connection]  # opens the drives (raises DriveOpenError)
    started: Callable[[Connection], str]  # the line said once every drive is enabled
    parameters: dict | None = None  # the parameters queryable's answer (None: the joint's)
    plot_title: str = ""


def _joint_setup(args: argparse.Namespace) -> "_Setup | int":
    """`actuatord` on one drive, a robot of one joint named by the prefix's last segment;
    the exit code 2 for bad input."""
    if args.prefix is None:
        args.prefix = telemetry.DEFAULT_PREFIX
    try:
        model = load_model_option(args.model)
        sim_model = with_truth_effects(model, args.truth_effect)
        schedule = fault_schedule(args)
        if schedule and not args.sim:
            raise ValueError("--inject-fault needs --sim")
        payload = payload_from_args(args)
        check_payload(model, payload)
        check_drive_arguments(args)
        check_eds(args.eds, model.parameters.drive_gain, esi=load_esi_option(args))
        check_key_expr("--prefix", args.prefix, wildcards=False)
        zenoh_config(args)  # its file and endpoints, before the controller is compiled
        settings = _settings(args, model)
        reference = _reference(args.reference, model)
        if args.plot:
            check_output_folder("--plot", args.plot)
        if args.report is not None:
            check_output_file("--report", args.report)
        # built (and compiled) before the drive is opened: a reference the model's limits
        # refuse (a velocity_max below the default sinusoid's peak) is bad input, not a crash
        try:
            # the default sinusoid too, before the compile: a first run's compile (half a
            # minute) is not waited for, nor said, before bad input is refused
            check_reference(reference, model.limits)
            with CompileNotice(PROG):  # a first run compiles the solver here
                batch = BatchMpc([JointProblem(model, settings, payload, reference)])
                process_image.compile_ahead()  # the bus's decode and encode, as the solver
        except ReferenceError as exc:
            shown = args.reference or "(default: the paper's sinusoid)"
            raise ValueError(f"--reference {shown[:60]} with the limits of the model "
                             f"{model.source}: {exc}") from None
    except (ModelFileError, BusSpecError, ReferenceError, ValueError) as exc:
        return usage_error(PROG, str(exc))
    name = args.prefix.rstrip("/").rsplit("/", 1)[-1]
    period = args.period_us * 1e-6
    title = "with current barrier" if not args.no_current_barrier else "no current barrier"
    if payload.mass:
        title = f"{payload.mass:g} kg payload, {title}"
    return _Setup(
        batch, [name], [model], [payload], period,
        lambda: open_drive(args, model, sim_model, payload, schedule, name, period=period),
        lambda connection: (f"{connection.address} on {connection.where} enabled; "
                            f"telemetry under {args.prefix}/"),
        plot_title=title)


def _run(args: argparse.Namespace, setup: _Setup, stop: threading.Event,
         threads: ThreadFailures) -> int:
    """Every joint in one cycle: exit 0 when the run ends as asked, 1 when a joint failed
    (every joint quick-stopped, the joint named), 2 for a drive that does not fit its joint's
    model (refused before any is enabled)."""
    from controller.telemetry import TelemetryPublisher
    from driver import DriveError, ProfileError
    from driver.clock import clock_for, collector_off_the_cycle

    # real-time priority from here on, once the solver is compiled (by the setup), not
    # before: a start-up's compiling at that priority starved the drives and the running
    # master on a 2-core host. Zenoh's and the publisher's threads inherit it: at normal
    # priority beside CPU-bound work the telemetry fell seconds behind the loop
    apply_real_time(args, PROG)
    try:
        session = open_session(args)
    except ValueError as exc:
        return usage_error(PROG, str(exc))
    publisher = TelemetryPublisher(session, args.prefix, telemetry.topics(len(setup.names)),
                                   ros2_domain=args.ros2)
    try:
        connection = setup.open()
    except DriveOpenError as exc:
        publisher.close()
        session.close()
        return job_error(PROG, str(exc))
    group = connection.group
    loop = ControlLoop(group, setup.batch,
                       LoopOptions(period=setup.period, clock=clock_for(args.lockstep),
                                   duration=args.duration, keep_history=bool(args.plot)),
                       (), lambda: publisher.dropped, stop, settle=TRACKING_SETTLE,
                       take_turn=publisher.take_turn, wire_subscribers=[publisher.publish])
    signal.signal(signal.SIGINT, lambda *_: loop.stop())
    signal.signal(signal.SIGTERM, lambda *_: loop.stop())
    failure = None
    try:  # from here on the drives are open: whatever happens, they are stopped and closed
        handlers = [RequestHandler(loop, j, model, payload, publisher.publish_audit)
                    for j, (model, payload) in enumerate(zip(setup.models, setup.payloads,
                                                             strict=True))]
        parameters = setup.parameters
        publisher.serve_json(telemetry.PARAMETERS, handlers[0].parameters if parameters is None
                             else lambda _: parameters)
        publisher.serve_requests(handlers)
        # the start-up heap collected and frozen before the drives are enabled: a full
        # collection of this heap held the interpreter past the slaves' 100 ms watchdog
        # (see driver.clock.collector_off_the_cycle)
        with collector_off_the_cycle():
            group.start(configured=loop.solve_first)
            loop.report.configure_us = group.bring_up.configure * 1e6
            loop.report.enable_us = group.bring_up.enable * 1e6
            print(f"actuatord: {setup.started(connection)}", flush=True)
            for clock in group.clocks:  # EtherCAT lines on distributed clocks
                print(f"actuatord: {clock.describe()}", flush=True)
            report = loop.run()
        if report.exit_code != 0:
            failure = report.reason
    except DriveError as exc:
        report = loop.report
        # a drive that does not fit its joint's model is refused before any is enabled
        unfit = isinstance(exc.__cause__, ProfileError)
        report.exit_code, report.reason = 2 if unfit else 1, str(exc)
        failure = str(exc)
        loop.fault(0.0, "drive", failure, QUICK_STOPPED)
    except Exception as exc:  # a bug or an input no check foresaw: the drives stop
        report = loop.report
        report.exit_code, report.reason = 1, internal_error(exc)
        failure = report.reason
    if threads.first is not None and failure is None:
        report.exit_code, report.reason = 1, threads.first
        failure = threads.first
    try:
        if failure is not None and report.exit_code == 1:
            states = group.quick_stop_all()
            print("actuatord: quick stop: " + ", ".join(f"{name} {state}"
                                                          for name, state in states),
                  flush=True)
    finally:
        connection.close()
        publisher.close()
        session.close()
    if failure is not None:
        (usage_error if report.exit_code == 2 else job_error)(PROG, failure)
    print(f"actuatord: {report.summary()}", flush=True)
    for clock in group.clocks:
        print(f"actuatord: {clock.summary()}", flush=True)
    _write_report(args, report)
    rms = loop.tracking_rms()
    print(f"actuatord: RMS tracking error after {TRACKING_SETTLE:g} s (mrad): " + ", ".join(
        f"{name} {1e3 * value:.2g}" for name, value in zip(loop.names, rms,
                                                           strict=True)), flush=True)
    if args.plot and report.history.get("t"):
        from controller.plots import save_figures

        for path in save_figures(report.history, setup.models[0].limits, Path(args.plot),
                                 setup.plot_title):
            print(f"actuatord: wrote {path}", flush=True)
    return report.exit_code


# --- a robot file: every joint in one cycle ---------------------------------------------------

# s: joints start where they rest, up to ~2 rad from their reference's start; at their
# velocity limits (3..5 rad/s) they reach it well within this, after which errors are tracking
TRACKING_SETTLE = 1.0
# options that name one joint's drive, model or reference; a robot file names each joint's
_SINGLE_JOINT_OPTIONS = (("--model", "model", None), ("--bus", "bus", None),
                         ("-i", "interface", None), ("-c", "channel", None),
                         ("--node-id", "node_id", None), ("--slave", "slave", None),
                         ("--eds", "eds", None), ("--esi", "esi", None),
                         ("--reference", "reference", None),
                         ("--plot", "plot", None), ("--can-log", "can_log", None),
                         ("--truth-effect", "truth_effect", []),
                         ("--payload-mass", "payload_mass", 0.0),
                         ("--no-current-barrier", "no_current_barrier", False))


def _robot_problems(args: argparse.Namespace, robot) -> list:
    """One optimal control problem per joint: the command line's horizon, step and weights,
    the robot file's weights and reference for the joint on top."""
    from robot.problems import joint_problems

    common = parse_assignments(args.weight, Weights.__dataclass_fields__, "--weight")
    if not 2 <= args.horizon <= MAX_HORIZON:
        raise ValueError(f"--horizon {args.horizon}: expected 2..{MAX_HORIZON} steps")
    try:
        problems = joint_problems(robot, OcpSettings(horizon=args.horizon, dt=args.dt), common)
    except ValueError as exc:
        raise ValueError(f"--weight/--dt for {exc}") from None
    for joint, problem in zip(robot.joints, problems, strict=True):
        try:
            _check_resolution(problem.settings, joint.model, args.period_us)
        except ValueError as exc:
            raise ValueError(f"joint {joint.name}: {exc}") from None
    return problems


def _robot_parameters(robot, problems: list) -> dict:
    """What the parameters queryable reports for a robot: every joint."""
    return {"robot": robot.name, "period_us": robot.period_us, "joints": [
        {"name": joint.name, "bus": joint.bus, "address": joint.address,
         "parameters": dataclasses.asdict(joint.model.parameters),
         "limits": vars(joint.model.limits), "provenance": joint.model.provenance,
         "settings": {"horizon": problem.settings.horizon, "dt": problem.settings.dt,
                      "weights": vars(problem.settings.weights),
                      "friction_sharpness": problem.settings.friction_sharpness,
                      "friction_sharpness_solved": problem.friction_sharpness_solved},
         "reference": {"kind": type(joint.reference).__name__.lower(), **vars(joint.reference)}}
        for joint, problem in zip(robot.joints, problems, strict=True)]}


def _robot_setup(args: argparse.Namespace) -> "_Setup | int":
    """`actuatord --robot FILE`: every joint of the file; the exit code 2 for a bad file or
    option."""
    from commands.sim_options import parse_joint_fault
    from driver.clock import clock_for
    from robot.description import RobotFileError, load_robot
    from robot.wiring import open_robot

    try:
        for option, key, default in _SINGLE_JOINT_OPTIONS:
            if getattr(args, key, default) != default:
                raise ValueError(f"--robot and {option}: the robot file names each joint's "
                                 "bus, model and reference")
        robot = load_robot(args.robot)
        if args.period_us != robot.period_us:
            raise ValueError(f"--period-us {args.period_us}: the robot file {args.robot} sets "
                             f"period_us = {robot.period_us}")
        check_drive_arguments(args, robot.buses())
        faults = [parse_joint_fault(text, [j.name for j in robot.joints])
                  for text in args.inject_fault]
        if faults and not args.sim:
            raise ValueError("--inject-fault needs --sim")
        args.prefix = args.prefix or f"robots/{robot.name}"
        check_key_expr("--prefix", args.prefix, wildcards=False)
        zenoh_config(args)  # its file and endpoints, before the controller is compiled
        if args.report is not None:
            check_output_file("--report", args.report, [("--robot", args.robot)])
        problems = _robot_problems(args, robot)
        with CompileNotice(PROG):
            batch = BatchMpc(problems)  # compiled before any drive is opened
            process_image.compile_ahead()  # the buses' decode and encode, as the solver
            if args.sim and any(is_ethercat(bus) for bus in robot.buses()):
                from sim_bus.line_physics import compile_ahead

                compile_ahead()  # the virtual line's batch, or its first cycle compiles it
    except (RobotFileError, BusSpecError, ValueError) as exc:
        return usage_error(PROG, str(exc))
    period = robot.period_us * 1e-6
    return _Setup(
        batch, [j.name for j in robot.joints], [j.model for j in robot.joints],
        [problem.payload for problem in problems], period,
        lambda: open_robot(robot, sim=args.sim, clock=clock_for(args.lockstep),
                           seed=args.seed, period=period, faults=faults),
        lambda connection: (f"{len(connection.group)} "
                            f"joint{'s' if len(connection.group) != 1 else ''} of {robot.name} on "
                            f"{', '.join(robot.buses())}{' (--sim)' if args.sim else ''} "
                            f"enabled; telemetry under {args.prefix}/"),
        parameters=_robot_parameters(robot, problems))


if __name__ == "__main__":
    sys.exit(main())
