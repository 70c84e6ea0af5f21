"""`bus-bench`: how fast the master and the virtual drive run, in lock-step.

Prints one JSON object: SYNC cycles per second with both in this process on python-can's
`virtual` bus, the SYNC -> TPDO sample latency and full SYNC -> TPDO -> RPDO cycle time with
`sim-bus` in a second process over `udp_multicast`, and, where this host can make a private
veth in a network namespace (root), the EtherCAT line with 1 and then 4 virtual slaves in a
second process: lock-step frames per second and the frame round trip at 1 kHz
(`driver.ethercat_bench.measure_line`). The host's CPU count and load average come with the
figures, which mean little without them.
"""

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import time

import numpy as np

from commands.log_options import (
    add_logging_argument,
    configure_logging,
    job_error,
    reports_failures,
)
from commands.parsing import (
    CommandParser,
    doc_description,
    int_range,
    positive_float,
    usage_error,
)
from driver.canopen_drive import CanOpenDrive, open_network

ETHERCAT_LINES = (1, 4)  # slaves on the measured lines


def _stage(text: str) -> None:
    """One progress line on stderr per measurement (the JSON result alone goes to stdout): the
    whole run takes 15-30 s."""
    print(f"bus-bench: {text}", file=sys.stderr, flush=True)


def _in_process(cycles: int) -> float:
    """SYNC cycles a second, master and virtual drive in this process on python-can's
    `virtual` bus, both on drive time."""
    from driver.clock import DriveClock
    from model.parameters import Payload, load_model
    from sim_bus.canopen_node import CanOpenNode
    from sim_bus.device import Cia402Device
    from sim_bus.plant import SensorNoise

    model = load_model()
    channel = f"virtual:bench-{random.getrandbits(32)}"
    sim_network = open_network(channel)
    sim = CanOpenNode(sim_network, 2, Cia402Device(model, Payload(), SensorNoise(), node_id=2),
                      clock=DriveClock())
    sim.boot()
    master = CanOpenDrive(open_network(channel), 2, velocity_limit=model.limits.velocity_max,
                          clock=DriveClock())
    try:
        master.start()
        start = time.perf_counter()
        for _ in range(cycles):
            master.sync()
            master.command_current(0.1)
        return cycles / (time.perf_counter() - start)
    finally:
        master.close()
        sim.close()
        sim_network.disconnect()


def _two_processes(cycles: int) -> dict:
    bus = f"udp_multicast:239.0.0.{random.randint(1, 250)}:{random.randint(20000, 60000)}"
    proc = subprocess.Popen([sys.executable, "-m", "commands.sim_bus", "--bus", bus],
                            stdout=subprocess.PIPE, text=True)
    try:
        if "ready" not in proc.stdout.readline():
            raise RuntimeError("sim-bus did not start")
        master = CanOpenDrive.open(bus, 2, velocity_limit=_velocity_limit())
        try:
            master.start()
            sample_latency, cycle_time = [], []
            for _ in range(cycles):
                t0 = time.perf_counter()
                master.sync()
                t1 = time.perf_counter()
                master.command_current(0.1)
                sample_latency.append(t1 - t0)
                cycle_time.append(time.perf_counter() - t0)
        finally:
            master.close()
    finally:
        proc.terminate()
        proc.wait(10)
    lat, cyc = np.array(sample_latency) * 1e6, np.array(cycle_time) * 1e6
    return {"sync_to_sample_median_us": round(float(np.median(lat)), 1),
            "sync_to_sample_p99_us": round(float(np.percentile(lat, 99)), 1),
            "sync_tpdo_rpdo_cycle_median_us": round(float(np.median(cyc)), 1),
            "sync_tpdo_rpdo_cycle_p99_us": round(float(np.percentile(cyc, 99)), 1),
            "cycles": cycles}


def _ethercat(cycles: int, sync: str, lines: tuple[int, ...] = ETHERCAT_LINES,
              period: float = 1e-3) -> list[dict] | None:
    """measure_line on a private veth for each line length in `lines`, the slaves in
    their own process (as sim-bus runs them); None, after one line on stderr saying why, when
    this host cannot make the link (no root, no namespaces, no raw sockets)."""
    from driver.ethercat_bench import measure_line
    from model.parameters import load_model
    from sim_bus.ethercat.netns import LinkUnavailable, SlaveProcess, VirtualLink

    try:
        link = VirtualLink()
    except LinkUnavailable as exc:
        print(f"bus-bench: EtherCAT part skipped: {exc} (a veth in a network namespace of "
              "its own needs root)", file=sys.stderr, flush=True)
        return None
    results = []
    with link:
        for slaves in lines:
            _stage(f"EtherCAT line of {slaves} virtual slave{'s' * (slaves > 1)} over a veth, "
                   f"{cycles} frames lock-step and {cycles} at {1 / period:g} Hz ...")
            with SlaveProcess(link, slaves, load_model()), link.entered():
                results.append(measure_line(link.master_port, slaves, cycles, period,
                                            sync=sync))
    return results


class _Stopped(BaseException):
    """A signal stopped the bench: raised where the main thread is, so every process,
    busy loop and network namespace it made is ended by the `with` and `finally` that made
    it (the default SIGTERM left them running: a `sim-bus` serving nobody, busy loops,
    namespaces). Not an Exception: nothing on the way treats it as a failed measurement."""


def _stop_on(signum: int, _frame) -> None:
    signal.signal(signum, signal.SIG_DFL)  # a second one ends the bench at once
    raise _Stopped(signal.Signals(signum).name)


def _velocity_limit() -> float:
    from model.parameters import load_model

    return load_model().limits.velocity_max


@reports_failures("bus-bench")
def main(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="bus-bench", description=doc_description(__doc__))
    parser.add_argument("--cycles", type=int_range(1, 10_000_000), default=5000,
                        help="cycles per measurement (default: %(default)s; the EtherCAT round "
                             "trips take that many ms of real time per line)")
    parser.add_argument("--robot", metavar="FILE",
                        help="instead: the robot file in real time, its virtual drives in one "
                             "process and actuatord in another, beside this machine's bare "
                             "1 kHz loop (`commands.robot_bench`; EtherCAT lines need root)")
    parser.add_argument("--duration", type=positive_float, default=10.0, metavar="S",
                        help="--robot: seconds of each run and of the bare loop "
                             "(default: %(default)s)")
    parser.add_argument("--starts", type=int_range(1, 1000), default=3, metavar="N",
                        help="--robot: runs started one after the other (default: %(default)s)")
    parser.add_argument("--sim", action="store_true",
                        help="--robot: the virtual drives embedded in actuatord's process "
                             "(`actuatord --robot --sim` in real time) instead of their own")
    parser.add_argument("--busy-loops", type=int_range(0, 64), default=0, metavar="N",
                        help="--robot: N CPU-bound processes at normal priority beside the "
                             "floor and every start, as on a busy host (default: %(default)s)")
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--no-ethercat", action="store_true", help="the CAN figures only")
    which.add_argument("--ethercat-only", action="store_true", help="the EtherCAT figures only")
    parser.add_argument("--sync", choices=("free_run", "dc"),
                        help="the EtherCAT lines' synchronization: free run (SM-synchronous) "
                             "or distributed clocks (SYNC0 every period, the master following "
                             "the reference clock; default: free_run, with --robot the robot "
                             "file's)")
    parser.add_argument("--slaves", type=int_range(1, 64), metavar="N",
                        help="one EtherCAT line of N slaves instead of the lines of "
                             f"{' and '.join(map(str, ETHERCAT_LINES))}")
    parser.add_argument("--period-us", type=int_range(100, 100_000), default=1000,
                        help="the EtherCAT lines' real-time period (us, default: %(default)s)")
    add_logging_argument(parser)
    args = parser.parse_args(argv)
    configure_logging(parser.prog, args.log_level)
    if args.robot is None and (args.sim or args.busy_loops):
        return usage_error(parser.prog, "--sim and --busy-loops go with --robot FILE")
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _stop_on)  # given back on return (`reports_failures`)
    try:
        return _measure(parser.prog, args)
    except _Stopped as stopped:
        return job_error(parser.prog, f"stopped by {stopped}: no figures (what it started "
                                      "has ended)")


def _measure(prog: str, args: argparse.Namespace) -> int:
    """What `main` measures, once its arguments are checked; its exit code."""
    from driver import DriveError

    result: dict = {"cpus": os.cpu_count(),
                    "load_average_1min": round(os.getloadavg()[0], 2)}
    if args.robot is not None:
        from commands.robot_bench import run as robot_real_time
        from robot.description import RobotFileError
        from sim_bus.ethercat.netns import LinkUnavailable

        try:
            result.update(robot_real_time(args.robot, args.duration, args.starts, args.sync,
                                          sim=args.sim, busy_loops=args.busy_loops))
        except RobotFileError as exc:
            return usage_error(prog, str(exc))
        except LinkUnavailable as exc:
            return job_error(prog, f"{args.robot}: its EtherCAT lines need a veth "
                                   f"between two network namespaces: {exc}")
        print(json.dumps(result))
        return 0
    try:
        if not args.ethercat_only:
            _stage(f"CAN, master and virtual drive in one process, {args.cycles} lock-step "
                   "cycles ...")
            result["in_process_drive_time_cycles_per_s"] = round(
                _in_process(args.cycles))
            _stage(f"CAN over udp_multicast, sim-bus in a second process, {args.cycles} "
                   "cycles ...")
            result["udp_multicast_two_processes"] = _two_processes(args.cycles)
        if not args.no_ethercat:
            lines = _ethercat(args.cycles, args.sync or "free_run",
                              ETHERCAT_LINES if args.slaves is None else (args.slaves,),
                              args.period_us * 1e-6)
            if lines is None and args.ethercat_only:
                return 1  # the one thing asked for cannot be measured here (said why)
            if lines is not None:
                result["ethercat_veth_two_processes"] = lines
    except (DriveError, RuntimeError, OSError) as exc:
        return job_error(prog, f"measurement failed: {exc}")
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
