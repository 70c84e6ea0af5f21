"""`bus-bench --robot FILE`: a robot in real time as it would run on its PC, the virtual drives
in one process (`sim-bus --robot`) and the master in another (`actuatord --robot`), started
`--starts` times, beside this machine's own floor (a bare 1 kHz loop) measured in the same
run: how many starts reached their first cycle and their end, missed cycles by cause, jitter,
the MPC tick and the master's own cost. `--sim` runs the drives embedded in the master's
process instead (`actuatord --robot --sim` in real time); `--busy-loops N` runs N CPU-bound
processes at normal priority beside the floor and every start, as a busy host has them.

The drives' process stands in for hardware, which has processors of its own: it runs on the
last CPU the bench may use and the master on the others (on a machine of one CPU, both on
it). Measured on talos_arm across processes (2 CPUs, 15 s runs, load 2.3-2.5): with both
free to run anywhere the drives (real-time priority above the master's, as hardware never
waits for the master's host) woke on the master's CPU at each SYNC and preempted it inside
its send, and 40 % of cycles were missed (jitter p99 1.2 ms); the drives alone on one CPU,
18 %; each on a CPU of its own, 1.2 % (jitter p99 183 us).

EtherCAT lines run over a veth between two network namespaces of the bench's own, each end
named as the robot file names the line (root); CAN buses, which this kind of machine has no
kernel driver for, run over `udp_multicast` (a group and port per bus). The robot file is
rewritten for that into a folder of the bench's own; the user's is only read."""

import contextlib
import json
import os
import random
import subprocess
import sys
import tempfile
import threading
import tomllib
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
import tomli_w

from driver.host_floor import FloorBeside, bare_loop
from protocol.bus_spec import is_ethercat, parse_bus_spec
from robot.description import load_robot, robot_path
from sim_bus.ethercat.netns import NamespacePair

START_TIMEOUT = 180.0  # s for sim-bus to build and serve every drive on a busy host
# s before a failed start's last cycle in which a stall of the host is named: a drive's
# watchdog or sync monitor trips within tens of ms of the silence that trips it, and the
# master finds out a few cycles later
FAILURE_LOOKBACK = 0.1


def stage(text: str) -> None:
    print(f"bus-bench: {text}", file=sys.stderr, flush=True)


def run(robot_file: str, duration: float, starts: int, sync: str | None = None, *,
        sim: bool = False, busy_loops: int = 0) -> dict:
    """Everything `bus-bench --robot` prints (one JSON object); `sync` ("free_run" or "dc"):
    every EtherCAT line of the robot on it instead of the robot file's own choice; `sim`: the
    drives embedded in the master's process; `busy_loops`: CPU-bound processes beside it."""
    robot = load_robot(robot_file)
    with contextlib.ExitStack() as stack:
        if busy_loops:
            stage(f"{busy_loops} CPU-bound loop{'s' * (busy_loops > 1)} beside everything")
            stack.enter_context(_busy_loops(busy_loops))
        stage(f"this machine's floor: a bare 1 kHz loop at real-time priority for "
              f"{duration:g} s")
        floor = bare_loop(duration)
        lines = sorted({parse_bus_spec(bus)["channel"] for bus in robot.buses()
                        if is_ethercat(bus)}) if not sim else []
        runs = []
        cpus = _cpus()
        folder = stack.enter_context(tempfile.TemporaryDirectory(prefix="bus-bench-"))
        # a shipped robot's name (`talos_arm`) as actuatord takes it
        path = _with_buses_here(robot_path(robot_file), Path(folder), sync)
        pair = stack.enter_context(NamespacePair(lines)) if lines else None
        for start in range(1, starts + 1):
            joints = len(robot.joints)
            stage(f"start {start}/{starts}: {joints} joint{'s' if joints != 1 else ''} of "
                  f"{robot.name}, "
                  f"{duration:g} s in real time{', drives embedded' if sim else ''}")
            with FloorBeside(sorted(os.sched_getaffinity(0)),
                             robot.period_us * 1e-6) as beside:
                one = _one_start(pair, path, duration, Path(folder) / f"run{start}.json",
                                 robot.period_us, sim, cpus)
            if one.get("cycles_from_s") is not None:
                one["floor_beside"] = beside.figures(one["cycles_from_s"], one["cycles_to_s"])
                # the run's own misses a stall of the host explains, and those it does not
                one["missed_in_host_stalls"] = beside.in_stalls(one.pop("missed_at_s"))
                if one.get("exit_code") not in (0, None):
                    # a start that failed: did the host take a CPU away just before?
                    end = one["cycles_to_s"]
                    one["host_stall_before_failure"] = beside.longest_stall(
                        end - FAILURE_LOOKBACK, end)
            runs.append(one)
    cycles = round(duration * 1e6 / robot.period_us)
    for one in runs:
        if "missed" in one:
            one["missed_percent"] = round(100 * one["missed"] / cycles, 3)
    missed = [one["missed_percent"] for one in runs if one["started"] and "missed_percent" in one]
    beside = [one["floor_beside"]["missed_percent"] for one in runs if "floor_beside" in one]
    return {
        "robot": robot.name, "joints": len(robot.joints), "duration_s": duration,
        "drives": "embedded" if sim else "own process", "busy_loops": busy_loops,
        "cpus": {"drives": sorted(cpus[0]), "master": sorted(cpus[1])}
        if cpus is not None and not sim else None,
        "ethercat_sync": {bus: sync or robot.sync(bus) for bus in robot.buses()
                          if is_ethercat(bus)},
        "floor": {"cycles": cycles, "missed": floor.missed_cycles,
                  "missed_percent": round(100 * floor.missed_cycles / cycles, 3),
                  "jitter_p99_us": round(floor.jitter_us.percentile(99), 1),
                  "jitter_max_us": round(floor.jitter_us.max, 1)},
        "starts": {"asked": starts, "started": sum(r["started"] for r in runs),
                   "ran_to_the_end": sum(r.get("exit_code") == 0 for r in runs)},
        # over the starts that ran: what a reader holds against 3x the floor
        "missed_percent": {"median": float(np.median(missed)), "max": max(missed)}
        if missed else None,
        # the floor beside each start, over that start's cycles (`driver.host_floor`)
        "floor_beside_percent": {"median": float(np.median(beside)), "max": max(beside)}
        if beside else None,
        "runs": runs,
    }


@contextlib.contextmanager
def _busy_loops(count: int) -> Iterator[None]:
    """`count` processes spinning at normal priority until the block ends."""
    loops = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
             for _ in range(count)]
    try:
        yield
    finally:
        for loop in loops:
            loop.kill()
            loop.wait()


def _cpus() -> tuple[set[int], set[int]] | None:
    """(the drives' CPUs, the master's): the last CPU this process may use, and the others;
    None on a single CPU."""
    allowed = sorted(os.sched_getaffinity(0))
    if len(allowed) < 2:
        return None
    return {allowed[-1]}, set(allowed[:-1])


def _place(process: subprocess.Popen, cpus: set[int] | None) -> None:
    """`process` on `cpus` (None: anywhere). Set as it starts, before the interpreter has
    started a thread of its own (they inherit it); it outlives `ip netns exec`'s exec."""
    if cpus is not None:
        try:
            os.sched_setaffinity(process.pid, cpus)
        except ProcessLookupError:
            pass  # it ended already: its exit code says why


def _one_start(pair: NamespacePair | None, path: Path, duration: float, report: Path,
               period_us: int, sim: bool = False,
               cpus: tuple[set[int], set[int]] | None = None) -> dict:
    """One start: the drives' process until ready (none with `sim`), actuatord for
    `duration`, the drives stopped; actuatord's figures (its --report) with whether it
    started. `cpus`: the drives' CPUs and the master's (`_cpus`)."""
    def inside(side: str, argv: list[str]) -> list[str]:
        return pair.command(side, argv) if pair is not None else argv

    if sim:
        return _master(inside, path, duration, report, period_us, ["--sim"])
    drives_cpus, master_cpus = cpus if cpus is not None else (None, None)

    errors = report.with_suffix(".sim-bus.err")
    with errors.open("w") as stderr:
        # stderr to a file and stdout drained after its first line: a pipe nobody reads
        # fills up with the drives' warnings and then stops the process that answers frames
        drives = subprocess.Popen(
            inside("line", [sys.executable, "-m", "commands.sim_bus", "--robot", str(path)]),
            stdout=subprocess.PIPE, stderr=stderr, text=True)
    _place(drives, drives_cpus)
    try:
        ready = drives.stdout.readline()
        if "ready" not in ready:
            return {"started": False, "error": f"sim-bus did not start: {ready.strip()} "
                                               f"{errors.read_text().strip()[-300:]}"}
        threading.Thread(target=drives.stdout.read, daemon=True).start()
        out = _master(inside, path, duration, report, period_us, cpus=master_cpus)
        if not out["started"]:  # the drives' side of it: e.g. why a slave refused a state
            out["drives_said"] = errors.read_text().strip()[-600:]
        return out
    finally:
        drives.send_signal(2)  # SIGINT: sim-bus reports and ends
        try:
            drives.wait(20)
        except subprocess.TimeoutExpired:
            drives.kill()
            drives.wait(10)


def _master(inside: Callable[[str, list[str]], list[str]], path: Path, duration: float,
            report: Path, period_us: int, extra: Sequence[str] = (),
            cpus: set[int] | None = None) -> dict:
    """actuatord on the robot for `duration` (on `cpus`, None: anywhere): its figures (its
    --report) with whether it started."""
    master = subprocess.Popen(
        inside("master", [sys.executable, "-m", "commands.actuatord", "--robot", str(path),
                          "--duration", f"{duration:g}", "--no-multicast-scouting",
                          # the MPC steps as the robot cycles (the default dt is 1 ms)
                          "--period-us", str(period_us), "--dt", f"{period_us * 1e-6:g}",
                          "--report", str(report), *extra]),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _place(master, cpus)
    try:
        stdout, stderr = master.communicate(timeout=duration * 20 + START_TIMEOUT)
    except BaseException:  # timed out, or the bench itself was stopped
        master.kill()
        master.communicate()
        raise
    out = {"started": " enabled;" in stdout}
    if report.exists():
        out.update(json.loads(report.read_text()))
    # an EtherCAT line on distributed clocks: its delays at start, its offset at the end
    clocks = [line.removeprefix("actuatord: ") for line in stdout.splitlines()
              if "distributed clocks" in line or "reference-clock offset" in line]
    if clocks:
        out["clocks"] = clocks
    errors = [line for line in stderr.splitlines() if ": error: " in line]
    if errors:
        out["error"] = errors[0]
    elif not out["started"]:  # no error of its own: a crash, a signal; what it left
        out["error"] = (f"actuatord ended with exit code {master.returncode} before its first "
                        f"cycle: {stderr.strip()[-600:]}")
    return out


def _with_buses_here(path: Path, folder: Path, sync: str | None = None) -> Path:
    """The robot file rewritten into `folder` for this machine: each CAN bus on a
    udp_multicast group and port of its own, model and EDS paths made absolute (they were
    relative to the original's folder), every EtherCAT line on `sync` when given."""
    doc = tomllib.loads(path.read_text(encoding="utf-8-sig"))
    home = path.resolve().parent
    buses: dict[str, str] = {}
    for joint in doc["joints"]:
        bus = joint["bus"]
        if not is_ethercat(bus):
            if bus not in buses:
                buses[bus] = (f"udp_multicast:239.74.{len(buses) + 1}.1:"
                              f"{random.randint(20000, 60000)}")
            joint["bus"] = buses[bus]
        for key in ("model", "eds"):
            if key in joint:
                joint[key] = str(home / joint[key])
    if "buses" in doc:
        doc["buses"] = {buses.get(bus, bus): settings for bus, settings in doc["buses"].items()}
    if sync is not None:
        for bus in {joint["bus"] for joint in doc["joints"] if is_ethercat(joint["bus"])}:
            doc.setdefault("buses", {}).setdefault(bus, {})["sync"] = sync
    rewritten = folder / path.name
    rewritten.write_text(tomli_w.dumps(doc))
    return rewritten
