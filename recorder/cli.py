"""`recorder`: run the exciting trajectory and record it, record live Zenoh telemetry, or
export a recording to CSV.

    recorder --exciting-trajectory [--bus vcan0 | --sim [--lockstep]] -o FILE.mcap
    recorder --zenoh KEYEXPR -o FILE.mcap [--duration S]
    recorder export FILE.mcap -o FILE.csv
"""

import argparse
import datetime
import queue
import signal
import sys
import threading
import time
from pathlib import Path

from model.effects import with_truth_effects
from model.parameters import ModelFileError, load_model, parse_payload
from protocol import telemetry
from protocol.bus_spec import BusSpecError, parse_bus_spec
from recorder.exciting import ExcitingTrajectory, SlowSinusoid
from recorder.recording import RecordingError

RECORDED_TOPICS = ("state", "command", "fault")  # what an experiment's recording keeps


def _usage_error(message: str) -> int:
    print(f"recorder: error: {message}", file=sys.stderr)
    return 2


def build_parser() -> argparse.ArgumentParser:
    from controller.zenoh_session import add_zenoh_arguments

    parser = argparse.ArgumentParser(
        prog="recorder", description=__doc__.splitlines()[0],
        epilog="`recorder export FILE.mcap -o FILE.csv` writes the CSV interchange format.")
    job = parser.add_mutually_exclusive_group(required=True)
    job.add_argument("--exciting-trajectory", action="store_true",
                     help="run the paper's exciting trajectory on the drive and record it")
    job.add_argument("--sinusoid", action="store_true",
                     help="track a slow sinusoid (-1.2 +/- 0.9 rad at 0.1 Hz) for --duration "
                          "(default 20 s) and record it")
    job.add_argument("--zenoh", metavar="KEYEXPR",
                     help="record live telemetry, e.g. 'actuators/elbow/**'")
    parser.add_argument("-o", "--output", required=True, metavar="FILE.mcap")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--bus", default="vcan0", help="bus spec (default: vcan0)")
    where.add_argument("--sim", action="store_true", help="embedded virtual drive")
    parser.add_argument("--lockstep", action="store_true", help="with --sim: faster than real time")
    parser.add_argument("--node-id", type=int, default=2)
    parser.add_argument("--model", help="nominal model TOML for the tracking feedforward "
                                        "(and for --sim's drive)")
    parser.add_argument("--payload-mass", type=float, default=0.0, metavar="KG")
    parser.add_argument("--payload-position", metavar="X,Y")
    defaults = ExcitingTrajectory()
    parser.add_argument("--position-low", type=float, default=defaults.position_low)
    parser.add_argument("--position-high", type=float, default=defaults.position_high)
    parser.add_argument("--velocity-min", type=float, default=defaults.velocity_min)
    parser.add_argument("--velocity-max", type=float, default=defaults.velocity_max)
    parser.add_argument("--steps", type=int, default=defaults.steps,
                        help="cruise velocities from min to max (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="--sim sensor-noise seed")
    parser.add_argument("--truth-effect", action="append", default=[], metavar="NAME:K=V,...",
                        help="--sim: hidden effect in the virtual drive's physics (as sim-bus)")
    parser.add_argument("--duration", type=float,
                        help="--zenoh: stop after S seconds; --sinusoid: its length")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_zenoh_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "export":
        return _export(argv[1:])
    args = build_parser().parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    if args.zenoh:
        return _record_zenoh(args, stop)
    return _record_trajectory(args, stop)


def _record_trajectory(args: argparse.Namespace, stop: threading.Event) -> int:
    try:
        model = load_model(args.model)
        sim_model = with_truth_effects(model, args.truth_effect)
        payload = parse_payload(args.payload_mass, args.payload_position)
        if args.sinusoid:
            trajectory = SlowSinusoid(duration=args.duration or SlowSinusoid.duration)
            trajectory_range = (trajectory.center - trajectory.amplitude,
                                trajectory.center + trajectory.amplitude)
        else:
            trajectory = ExcitingTrajectory(args.position_low, args.position_high,
                                            args.velocity_min, args.velocity_max, args.steps)
            trajectory_range = (trajectory.position_low, trajectory.position_high)
        if not args.sim:
            parse_bus_spec(args.bus)
        if args.lockstep and not args.sim:
            raise ValueError("--lockstep needs --sim")
        limits = model.limits
        if not (limits.position_min <= trajectory_range[0]
                and trajectory_range[1] <= limits.position_max):
            raise ValueError(f"trajectory [{trajectory_range[0]}, {trajectory_range[1]}] rad "
                             f"leaves the model's limits [{limits.position_min}, "
                             f"{limits.position_max}] rad")
    except (ModelFileError, BusSpecError, ValueError) as exc:
        return _usage_error(str(exc))

    from driver import DriveError
    from driver.canopen_drive import CanOpenDrive
    from recorder.experiment import run_trajectory
    from recorder.mcap_io import McapRecorder
    from recorder.tracking import TrackingLaw

    sim = None
    bus = args.bus
    if args.sim:
        from sim_bus.embedded import EmbeddedDrive
        from sim_bus.plant import SensorNoise

        sim = EmbeddedDrive(sim_model, payload, SensorNoise(seed=args.seed), args.node_id)
    metadata = {
        "payload_mass": payload.mass, "payload_position": f"{payload.x},{payload.y}",
        "experiment": "sinusoid" if args.sinusoid else "exciting_trajectory",
        "trajectory": repr(trajectory), "truth_effects": ";".join(args.truth_effect),
        "model": model.source, "bus": "sim" if args.sim else args.bus,
        "node_id": args.node_id, "period_s": 1e-3,
        "recorded_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}
    try:
        drive = (CanOpenDrive(sim.master_network, args.node_id) if sim is not None
                 else CanOpenDrive.open(bus, args.node_id))
    except Exception as exc:
        print(f"recorder: error: cannot open bus {bus!r}: {exc}", file=sys.stderr)
        return 1
    writer = McapRecorder(args.output, metadata)
    law = TrackingLaw(model.parameters.with_payload(payload), model.limits.current_max)
    bar = _progress(args.no_progress, trajectory.duration)
    started = time.perf_counter()
    code, samples = 0, 0
    try:
        drive.start()
        report = run_trajectory(drive, trajectory, law, model.limits,
                                [writer.subscriber(RECORDED_TOPICS)], args.lockstep, bar, stop)
        samples = report.cycles
        if stop.is_set():
            code = 1
            print(f"recorder: interrupted after {samples} samples", file=sys.stderr)
        elif report.exit_code != 0:
            code = report.exit_code
            print(f"recorder: error: {report.reason}", file=sys.stderr)
    except DriveError as exc:
        code = 1
        print(f"recorder: error: {exc}", file=sys.stderr)
    finally:
        drive.close()
        writer.close()
        if sim is not None:
            sim.close()
    elapsed = time.perf_counter() - started
    bar(None)
    print(f"recorder: {samples} samples ({samples / 1000:.1f} s of drive time) in {elapsed:.1f} s "
          f"(real-time factor {samples / 1000 / elapsed:.2f}) -> {args.output}", flush=True)
    return code


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
    from controller.zenoh_session import open_session
    from recorder.mcap_io import McapRecorder

    try:
        session = open_session(args)
    except ValueError as exc:
        return _usage_error(str(exc))
    received: queue.Queue = queue.Queue()
    subscriber = session.declare_subscriber(
        args.zenoh, lambda sample: received.put((str(sample.key_expr),
                                                 sample.payload.to_bytes(), time.time_ns())))
    writer = McapRecorder(args.output, {"source": f"zenoh {args.zenoh}"})
    print(f"recorder: recording {args.zenoh} -> {args.output}", flush=True)
    deadline = time.monotonic() + args.duration if args.duration else None
    skipped = 0
    try:
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            try:
                key, data, log_time = received.get(timeout=0.1)
            except queue.Empty:
                continue
            message = telemetry.TOPICS.get(key.rsplit("/", 1)[-1])
            if message is None:
                skipped += 1
                continue
            writer.write(writer.channel(key, message), log_time, data)
    finally:
        subscriber.undeclare()
        session.close()
        while not received.empty():
            key, data, log_time = received.get()
            message = telemetry.TOPICS.get(key.rsplit("/", 1)[-1])
            if message is not None:
                writer.write(writer.channel(key, message), log_time, data)
        writer.close()
    print(f"recorder: {writer.messages} messages ({skipped} on keys without a schema skipped) "
          f"-> {args.output}", flush=True)
    return 0


def _export(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="recorder export",
                                     description="MCAP recording to the CSV contract")
    parser.add_argument("recording", metavar="FILE.mcap")
    parser.add_argument("-o", "--output", required=True, metavar="FILE.csv")
    args = parser.parse_args(argv)
    from recorder.csv_io import write_csv
    from recorder.recording import load_recording

    try:
        recording = load_recording(args.recording)
    except RecordingError as exc:
        return _usage_error(str(exc))
    write_csv(recording, Path(args.output))
    print(f"recorder: {len(recording)} samples -> {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
