"""`recorder`: run the exciting trajectory (or a slow sinusoid) on a drive and record it,
record live Zenoh telemetry, export a recording to CSV or as a ROS 2 bag, or repair one.

    recorder --exciting-trajectory [--bus vcan0 | --sim [--lockstep]] -o FILE.mcap
    recorder --sinusoid [--duration S] [--bus vcan0 | --sim [--lockstep]] -o FILE.mcap
    recorder --zenoh KEYEXPR -o FILE.mcap [--duration S]
    recorder export FILE.mcap -o FILE.csv
    recorder export --ros2 FILE.mcap -o BAG.mcap
    recorder repair FILE.mcap -o REPAIRED.mcap
"""

import argparse
import datetime
import queue
import signal
import sys
import threading
import time
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
from commands.file_options import check_distinct_outputs, check_output_file, option_inputs
from commands.first_run import CompileNotice
from commands.log_options import (
    add_logging_argument,
    configure_logging,
    job_error,
    reports_failures,
)
from commands.model_options import (
    add_model_argument,
    add_payload_arguments,
    check_payload,
    load_model_option,
    payload_from_args,
)
from commands.parsing import (
    CommandParser,
    doc_description,
    finite_float,
    int_range,
    positive_float,
    usage_error,
)
from commands.sim_options import add_virtual_drive_arguments, with_truth_effects
from commands.zenoh_options import (
    add_zenoh_arguments,
    check_key_expr,
    open_session,
    zenoh_config,
)
from model.parameters import ModelFileError
from protocol import telemetry
from protocol.bus_spec import BusSpecError
from recorder.exciting import ExcitingTrajectory, SlowSinusoid
from recorder.reader import load_recording
from recorder.recording import RecordingError
from robot.wiring import DriveOpenError, open_joint

PROG = "recorder"
# what an experiment's recording keeps (loop_stats: the loop's jitter and the tracking law's
# decide time, once a second, for the experiment layout's timing panel)
RECORDED_TOPICS = ("state", "command", "fault", "loop_stats")
ELBOW_MARGIN = 0.15  # rad: the exciting trajectory's default margin inside the elbow's limits
# the options that choose or shape a drive: meaningless for --zenoh, which drives nothing
_DRIVE_OPTIONS = (("--sim", "sim"), ("--lockstep", "lockstep"), ("--bus", "bus"),
                  ("-i", "interface"), ("-c", "channel"), ("--node-id", "node_id"),
                  ("--slave", "slave"), ("--eds", "eds"), ("--esi", "esi"),
                  ("--can-log", "can_log"), ("--model", "model"), ("--robot", "robot"),
                  ("--joint", "joint"), ("--payload-position", "payload_position"),
                  ("--truth-effect", "truth_effect"))
MAX_RUN = 3600.0  # s of drive time in one recording (3.6 M samples, some 500 MB of MCAP)


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(
        prog=PROG, description=doc_description(__doc__),
        epilog="`recorder export FILE.mcap -o FILE.csv` writes the CSV interchange format, "
               "`recorder export --ros2 FILE.mcap -o BAG.mcap` a ROS 2 bag; `recorder repair "
               "FILE.mcap -o REPAIRED.mcap` rewrites a killed, truncated or damaged recording "
               "as a complete MCAP file.")
    job = parser.add_mutually_exclusive_group(required=True)
    job.add_argument("--exciting-trajectory", action="store_true",
                     help="run the paper's exciting trajectory on the drive and record it")
    job.add_argument("--sinusoid", action="store_true",
                     help="track a slow sinusoid (-1.2 +/- 0.9 rad at 0.1 Hz) for --duration "
                          "(default 20 s) and record it")
    job.add_argument("--zenoh", metavar="KEYEXPR",
                     help="record live telemetry, e.g. 'actuators/elbow/**'")
    parser.add_argument("-o", "--output", required=True, metavar="FILE.mcap")
    add_bus_arguments(parser)
    add_model_argument(parser, help="nominal model TOML for the tracking feedforward (and for "
                                    "--sim's drive)")
    add_payload_arguments(parser)
    defaults = ExcitingTrajectory()
    parser.add_argument("--position-low", type=finite_float, default=defaults.position_low,
                        metavar="RAD", help="the exciting trajectory's lower end (rad, default: "
                                            "%(default)s; with --robot 0.15 rad inside the "
                                            "joint's lower limit)")
    parser.add_argument("--position-high", type=finite_float, default=defaults.position_high,
                        metavar="RAD", help="its upper end (rad, default: %(default)s; with "
                                            "--robot 0.15 rad inside the joint's upper limit)")
    parser.add_argument("--velocity-min", type=positive_float, default=defaults.velocity_min,
                        metavar="RAD/S", help="the first cruise velocity (rad/s, default: "
                                              "%(default)s)")
    parser.add_argument("--velocity-max", type=positive_float, default=defaults.velocity_max,
                        metavar="RAD/S", help="the last cruise velocity (rad/s, default: "
                                              "%(default)s; with --robot at most half the "
                                              "joint's velocity limit)")
    parser.add_argument("--steps", type=int_range(1, 1000), default=defaults.steps,
                        help="cruise velocities from min to max (default: %(default)s)")
    add_virtual_drive_arguments(parser, faults=False)
    add_real_time_argument(parser)
    parser.add_argument("--duration", type=positive_float, metavar="S",
                        help="--zenoh: stop after S seconds; --sinusoid: its length")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--robot", metavar="FILE",
                        help="record one joint of a robot file (with --joint): its bus, node id, "
                             "EDS and model from the file; the other joints are not started "
                             "(their drives stay disabled, brakes engaged); the trajectory's "
                             "defaults fit the joint's range")
    parser.add_argument("--joint", metavar="NAME", help="with --robot: the joint to record")
    add_zenoh_arguments(parser)
    add_logging_argument(parser)
    return parser


@reports_failures(PROG)
def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "export":
        return _export(argv[1:])
    if argv and argv[0] == "repair":
        return _repair(argv[1:])
    args = build_parser().parse_args(argv)
    configure_logging(PROG, args.log_level)
    try:
        check_output_file("-o", args.output, option_inputs(args))
        check_distinct_outputs([("-o", args.output), ("--can-log", args.can_log)])
        if args.zenoh is not None:  # '' too: an empty key expression is refused, not falsy
            check_key_expr("--zenoh", args.zenoh, wildcards=True)
            for option, key in _DRIVE_OPTIONS:
                if getattr(args, key, None) not in (None, False, []):
                    raise ValueError(f"{option}: --zenoh records telemetry and drives "
                                     "nothing; expected --exciting-trajectory or --sinusoid")
            zenoh_config(args)
    except ValueError as exc:
        return usage_error(PROG, str(exc))
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if args.zenoh is not None:
        return _record_zenoh(args, stop)
    return _record_trajectory(args, stop)


def _robot_joint(args: argparse.Namespace):
    """(robot, joint) for --robot/--joint, the trajectory's defaults fitted to the joint;
    (None, None) without --robot. ValueError names the option."""
    from robot.description import load_robot

    if args.robot is None:
        if args.joint is not None:
            raise ValueError("--joint needs --robot")
        return None, None
    for option, key, default in (("--model", "model", None), ("--bus", "bus", None),
                                 ("-i", "interface", None), ("-c", "channel", None),
                                 ("--node-id", "node_id", None), ("--slave", "slave", None),
                                 ("--eds", "eds", None), ("--esi", "esi", None)):
        if getattr(args, key, default) != default:
            raise ValueError(f"--robot and {option}: the robot file names the joint's bus, "
                             "node id or slave position, EDS and model")
    robot = load_robot(args.robot)
    names = [j.name for j in robot.joints]
    if args.joint not in names:
        raise ValueError(f"--joint {args.joint}: expected one of {', '.join(names)}")
    joint = robot.joints[names.index(args.joint)]
    limits, defaults = joint.model.limits, ExcitingTrajectory()
    # the elbow's defaults keep 0.15 rad inside its limits and cruise up to half its velocity
    # limit: the same margins for this joint, where the option was left at the elbow's value
    if args.position_low == defaults.position_low:
        args.position_low = limits.position_min + ELBOW_MARGIN
    if args.position_high == defaults.position_high:
        args.position_high = limits.position_max - ELBOW_MARGIN
    if args.velocity_max == defaults.velocity_max:
        args.velocity_max = min(defaults.velocity_max, 0.5 * limits.velocity_max)
    args.velocity_min = min(args.velocity_min, args.velocity_max)
    return robot, joint


def _record_trajectory(args: argparse.Namespace, stop: threading.Event) -> int:
    try:
        robot, joint = _robot_joint(args)
        model = load_model_option(args.model) if joint is None else joint.model
        sim_model = with_truth_effects(model, args.truth_effect)
        payload = payload_from_args(args)
        check_payload(model, payload)
        if args.sinusoid:
            trajectory = SlowSinusoid(duration=args.duration or SlowSinusoid.duration)
            trajectory_range = (trajectory.center - trajectory.amplitude,
                                trajectory.center + trajectory.amplitude)
        else:
            trajectory = ExcitingTrajectory(args.position_low, args.position_high,
                                            args.velocity_min, args.velocity_max, args.steps)
            trajectory_range = (trajectory.position_low, trajectory.position_high)
        check_drive_arguments(args, None if robot is None else [joint.bus])
        check_eds(args.eds, model.parameters.drive_gain, esi=load_esi_option(args))
        limits = model.limits
        if not args.sinusoid and not args.velocity_max <= limits.velocity_max:
            raise ValueError(f"--velocity-max {args.velocity_max:g} rad/s: expected at most "
                             f"the model's velocity limit {limits.velocity_max:g} rad/s")
        if not trajectory.duration <= MAX_RUN:
            shown = (f"--duration {args.duration:g} s" if args.sinusoid else
                     f"--velocity-min {args.velocity_min:g} rad/s")
            raise ValueError(f"{shown}: the trajectory would last {trajectory.duration:.3g} s; "
                             f"expected at most {MAX_RUN:g} s in one recording")
        if not (limits.position_min <= trajectory_range[0]
                and trajectory_range[1] <= limits.position_max):
            raise ValueError(f"trajectory [{trajectory_range[0]}, {trajectory_range[1]}] rad "
                             f"leaves the model's limits [{limits.position_min}, "
                             f"{limits.position_max}] rad")
    except (ModelFileError, BusSpecError, ValueError) as exc:
        return usage_error(PROG, str(exc))

    # the bus's decode and encode loaded (compiled on a first run) before any drive is enabled
    # and before the real-time priority, at which a compile starves the drives
    from driver import DriveError, ProfileError, process_image
    from driver.clock import clock_for, collector_off_the_cycle
    from recorder.experiment import run_trajectory
    from recorder.mcap_io import McapRecorder
    from recorder.tracking import TrackingLaw

    process_image.compile_ahead()
    apply_real_time(args, PROG)  # before the drive's threads start: they inherit it
    # a first run compiles the physics (--sim's drive, while it opens) and the tracking law
    # (its first sample); a real bus's opening is not counted
    notice = CompileNotice(PROG) if args.sim else None
    try:
        connection = (open_drive(args, model, sim_model, payload) if joint is None else
                      open_joint(robot, joint, sim_model, payload, sim=args.sim,
                                 clock=clock_for(args.lockstep), seed=args.seed))
    except DriveOpenError as exc:
        if notice is not None:
            notice.done()
        return job_error(PROG, str(exc))
    notice = notice or CompileNotice(PROG)
    group = connection.group
    metadata = {
        "payload_mass": payload.mass, "payload_position": f"{payload.x},{payload.y}",
        "experiment": "sinusoid" if args.sinusoid else "exciting_trajectory",
        "trajectory": repr(trajectory), "truth_effects": ";".join(args.truth_effect),
        "model": model.source, "bus": "sim" if args.sim else connection.where,
        # "node 2" / "slave 0": a CAN drive keeps its node_id key, a slave gets its own
        **_address_metadata(connection.address), "period_s": 1e-3,
        "robot": "" if robot is None else str(robot.source),
        "joint": "" if joint is None else joint.name,
        "recorded_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}
    try:  # before the drive runs
        writer = McapRecorder(args.output, metadata, on_failure=stop.set)
    except OSError as exc:
        notice.done()
        connection.close()
        return job_error(PROG, f"-o {args.output}: cannot write: {exc.strerror or exc}")
    # channels named as the Zenoh keys, so a Foxglove layout serves live data and both recordings
    record = writer.subscriber(RECORDED_TOPICS, telemetry.DEFAULT_PREFIX)
    state_channel = writer.channel(telemetry.key_expr(telemetry.DEFAULT_PREFIX, "state"), "State")
    law = TrackingLaw(model.parameters.with_payload(payload), model.limits.current_max)
    shown = _progress(args.no_progress, trajectory.duration)

    def bar(fraction: float | None) -> None:
        notice.done()  # the first sample is in: the compiled code runs
        shown(fraction)

    started = time.perf_counter()
    code = 0
    try:
        group.start()
        with collector_off_the_cycle():
            report = run_trajectory(group, trajectory, law, model.limits, (),
                                    clock_for(args.lockstep), bar, stop, [record])
        if writer.failure is not None:
            code = 1  # reported below, once the file is closed
        elif stop.is_set():
            code = 1
            print(f"{PROG}: interrupted after {writer.messages_on(state_channel)} samples",
                  file=sys.stderr)
        elif report.exit_code != 0:
            code = job_error(PROG, report.reason)
    except DriveError as exc:
        # a drive that does not fit the model is refused before enabling: bad input
        unfit = isinstance(exc.__cause__, ProfileError)
        code = (usage_error if unfit else job_error)(PROG, str(exc))
    finally:
        connection.close()
        # the samples that reached the writer, however the run ended
        samples = writer.messages_on(state_channel)
        if code != 0 and samples == 0:
            writer.discard()  # failed before its first sample: leave no file
        else:
            writer.close()
    if writer.failure is not None:
        code = job_error(PROG, _write_failure(args.output, writer.failure, samples))
    elapsed = time.perf_counter() - started
    bar(None)
    output = args.output if samples else "no file written"
    print(f"recorder: {samples} samples ({samples / 1000:.1f} s of drive time) in {elapsed:.1f} s "
          f"(real-time factor {samples / 1000 / elapsed:.2f}) -> {output}", flush=True)
    return code


def _write_failure(path: str, exc: OSError, samples: int) -> str:
    """One line for a recording that could not be written to the end (a full disk): what was
    kept and how to make it whole."""
    return (f"-o {path}: cannot write: {exc.strerror or exc} after {samples} samples; the "
            f"file ends at its last complete chunk: `recorder repair {path} -o "
            "REPAIRED.mcap` keeps them")


def _address_metadata(address: str) -> dict[str, str | int]:
    """{'node_id': 2, 'slave': ''} for "node 2", {'node_id': '', 'slave': 0} for "slave 0"."""
    kind, _, number = address.partition(" ")
    return {"node_id": int(number) if kind == "node" else "",
            "slave": int(number) if kind == "slave" else ""}


def _progress(disabled: bool, total: float):
    """A tqdm bar fed with fractions; None closes it."""
    from tqdm import tqdm

    bar = tqdm(total=round(total, 1), unit="s", disable=disabled, file=sys.stderr,
               desc="trajectory", leave=False)

    def update(fraction: float | None) -> None:
        if fraction is None:
            bar.close()
            return
        bar.n = round(fraction * total, 1)
        bar.refresh()

    return update


def _record_zenoh(args: argparse.Namespace, stop: threading.Event) -> int:
    from recorder.mcap_io import McapRecorder

    try:
        session = open_session(args)
    except ValueError as exc:
        return usage_error(PROG, str(exc))
    try:
        writer = McapRecorder(args.output, {"source": f"zenoh {args.zenoh}"},
                              on_failure=stop.set)
    except OSError as exc:
        session.close()
        return job_error(PROG, f"-o {args.output}: cannot write: {exc.strerror or exc}")
    received: queue.Queue = queue.Queue()
    subscriber = session.declare_subscriber(
        args.zenoh, lambda sample: received.put((str(sample.key_expr),
                                                 sample.payload.to_bytes(), time.time_ns())))
    print(f"recorder: recording {args.zenoh} -> {args.output}", flush=True)
    deadline = time.monotonic() + args.duration if args.duration else None
    skipped = 0
    try:
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            try:
                key, data, arrival = received.get(timeout=0.1)
            except queue.Empty:
                continue
            skipped += not writer.write_sample(key, data, arrival)
    finally:
        subscriber.undeclare()
        session.close()
        while not received.empty():
            skipped += not writer.write_sample(*received.get())
        writer.close()
    if writer.failure is not None:
        return job_error(PROG, _write_failure(args.output, writer.failure, writer.messages))
    print(f"recorder: {writer.messages} messages ({skipped} on keys without a schema skipped) "
          f"-> {args.output}", flush=True)
    return 0


def _export(argv: list[str]) -> int:
    parser = CommandParser(
        prog=f"{PROG} export",
        description="Write a recording in the CSV interchange format (t,q,current,"
                    "joint_torque with # key=value metadata) or, with --ros2, as a ROS 2 "
                    "bag: an MCAP file of profile ros2 with sensor_msgs/msg/JointState on "
                    "/joint_states, which rosbags reads.")
    parser.add_argument("recording", metavar="FILE.mcap")
    parser.add_argument("-o", "--output", required=True, metavar="FILE.csv|FILE.mcap")
    parser.add_argument("--ros2", action="store_true",
                        help="write a ROS 2 MCAP (ROS 2 Jazzy types) instead of CSV; every "
                             "joint-state sample, stamped at its drive time on the run's "
                             "time base")
    add_logging_argument(parser)
    args = parser.parse_args(argv)
    configure_logging(PROG, args.log_level)
    from recorder.csv_io import write_csv
    from recorder.reader import is_mcap

    try:
        check_output_file("-o", args.output, [("FILE.mcap", args.recording)])
        if args.ros2:  # a robot's recording has no single-joint State: not load_recording
            if not is_mcap(args.recording):
                raise ValueError(f"--ros2: {args.recording} is CSV; the ROS 2 export reads "
                                 "MCAP recordings (CSV carries no velocity)")
            from recorder.ros2_export import export_ros2

            exported = export_ros2(args.recording, args.output)
            print(f"recorder: {exported.summary()} -> {args.output}")
            return 0
        recording = load_recording(args.recording)
    except (RecordingError, ValueError) as exc:
        return usage_error(PROG, str(exc))
    except OSError as exc:
        return usage_error(PROG, f"-o {args.output}: cannot write: {exc.strerror}")
    try:
        write_csv(recording, Path(args.output))
    except OSError as exc:  # a full disk: nothing is left behind (written whole or not)
        return job_error(PROG, f"-o {args.output}: cannot write: {exc.strerror or exc}")
    print(f"recorder: {len(recording)} samples -> {args.output}")
    return 0


def _repair(argv: list[str]) -> int:
    parser = CommandParser(
        prog=f"{PROG} repair",
        description="rewrite a killed, truncated or damaged MCAP recording as a complete one "
                    "(summary, indexes, statistics) keeping every sound chunk")
    parser.add_argument("recording", metavar="FILE.mcap")
    parser.add_argument("-o", "--output", required=True, metavar="REPAIRED.mcap")
    add_logging_argument(parser)
    args = parser.parse_args(argv)
    configure_logging(PROG, args.log_level)
    from recorder.repair import repair_recording

    try:
        check_output_file("-o", args.output)  # the same file: refused by repair, naming it
        report = repair_recording(args.recording, args.output)
    except (RecordingError, ValueError) as exc:
        return usage_error(PROG, str(exc))
    except OSError as exc:  # a full disk: the source is untouched, no partial copy is left
        return job_error(PROG, f"-o {args.output}: cannot write: {exc.strerror or exc}")
    print(f"recorder: {report.summary()} -> {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
