"""The commands over EtherCAT, run as a user runs them: `sim-bus` serving a line of virtual
slaves on one end of a veth, `actuatord` and `recorder` driving it from the other, each its
own process inside a network namespace of the test's own (`ip netns exec`). Lock-step runs
check the counts exactly; the one real-time run is the lost line. Bad input is refused in one
line before anything opens."""

import importlib
import logging
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pysoem
import pytest

from protocol import esi_path
from protocol.esi import load_esi
from recorder.reader import load_recording
from sim_bus.ethercat.netns import VirtualLink

pytestmark = pytest.mark.subprocess  # runs the commands as processes

REPO = Path(__file__).resolve().parent.parent
ZENOH = "--no-multicast-scouting"
STOP_WITHIN = 2.0  # s from SIGTERM/SIGINT to sim-bus's end report


def command(link: VirtualLink | None, module: str, *args: str) -> list[str]:
    """A console script's module, inside the link's namespace when there is one."""
    inside = ["ip", "netns", "exec", link.name] if link is not None else []
    return [*inside, sys.executable, "-m", f"commands.{module}", *args]


def run(link: VirtualLink | None, module: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(command(link, module, *args), capture_output=True, text=True,
                          timeout=120, cwd=REPO)


@contextmanager
def sim_bus(link: VirtualLink, *extra: str):
    """`sim-bus --bus ethercat:ecs0` in the namespace (`extra` starting with --robot: the
    file's lines instead), up once it says ready."""
    where = [] if extra[:1] == ("--robot",) else ["--bus", f"ethercat:{link.line_port}"]
    proc = subprocess.Popen(command(link, "sim_bus", *where, *extra),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    try:
        line = proc.stdout.readline()
        assert "ready" in line, f"sim-bus did not start: {line!r} {proc.stderr.read()}"
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(10)
        proc.stdout.close()
        proc.stderr.close()


def stop(proc: subprocess.Popen, sig: int = signal.SIGTERM) -> str:
    """Signal sim-bus; its end report, which must come within STOP_WITHIN, and a clean exit."""
    sent = time.monotonic()
    proc.send_signal(sig)
    report = proc.stdout.readline()
    took = time.monotonic() - sent
    assert proc.wait(10) == 0, proc.stderr.read()
    assert "stopped" in report, report
    assert took < STOP_WITHIN, f"sim-bus took {took:.2f} s to stop"
    return report


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if ": error: " in line]


@pytest.mark.real_time
def test_actuatord_runs_the_mpc_over_ethercat_for_5_s_in_lockstep(link):
    with sim_bus(link) as slaves:
        result = run(link, "actuatord", "--bus", f"ethercat:{link.master_port}", "--lockstep",
                     "--duration", "5", ZENOH)
        report = stop(slaves)
    assert result.returncode == 0, result.stderr
    assert f"slave 0 on ethercat:{link.master_port} enabled" in result.stdout
    assert "5000 cycles, 0 missed" in result.stdout and "ran 5.0 s" in result.stdout
    # the slave ran a device cycle per frame that wrote its outputs: the 5000 and bring-up's
    # (the enable sequence's frames, a read or a write each, and the disable's on close)
    cycles = int(report.split("slave 0 ")[1].split(" cycles")[0])
    assert 5000 <= cycles <= 5020, report
    assert "drive 'switch on disabled'" in report  # left disabled by the master at exit


@pytest.mark.real_time
def test_a_lost_line_stops_actuatord_in_real_time_naming_the_slave(link):
    with sim_bus(link) as slaves:
        actuatord = subprocess.Popen(
            command(link, "actuatord", "--bus", f"ethercat:{link.master_port}", ZENOH,
                    "--reference", '{"kind": "setpoint", "position": -1.0}'),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
        try:
            line = actuatord.stdout.readline()
            assert "enabled" in line, f"{line!r} {actuatord.stderr.read()}"
            time.sleep(0.5)
            assert actuatord.poll() is None, actuatord.stderr.read()  # running in real time
            slaves.kill()  # the line loses power
            lost = time.monotonic()
            code = actuatord.wait(15)
            took = time.monotonic() - lost
            stdout, stderr = actuatord.communicate()
        finally:
            if actuatord.poll() is None:
                actuatord.kill()
                actuatord.wait(10)
    assert code == 1, stderr
    assert took < 5.0, f"actuatord took {took:.1f} s to stop"
    errors = error_lines(stderr)
    assert len(errors) == 1, stderr
    assert f"EtherCAT {link.master_port}" in errors[0] and "slave 0 lost" in errors[0], errors
    assert "drive failed" in stdout  # the summary names the cause too


@pytest.mark.real_time
def test_recorder_records_a_sinusoid_over_ethercat(link, tmp_path):
    output = tmp_path / "sinusoid.mcap"
    with sim_bus(link) as slaves:
        result = run(link, "recorder", "--bus", f"ethercat:{link.master_port}", "--lockstep",
                     "--sinusoid", "--duration", "2", "-o", str(output), "--no-progress")
        stop(slaves)
    assert result.returncode == 0, result.stderr
    recording = load_recording(output)
    assert len(recording) == 2001  # the first sample at t = 0, then one a cycle for 2 s
    assert recording.metadata["bus"] == f"ethercat:{link.master_port}"
    assert recording.metadata["slave"] == "0"
    assert np.ptp(recording.q) > 0.5  # rad: the joint followed the sinusoid's first 2 s


@pytest.mark.real_time
def test_sim_bus_serves_slaves_that_soem_finds_and_reports_each_on_sigint(link):
    esi = load_esi(esi_path())
    with sim_bus(link, "--slaves", "2") as slaves:
        with link.entered():
            master = pysoem.Master()
            master.open(link.master_port)
            try:
                assert master.config_init() == 2
                assert [(s.man, s.id, s.rev) for s in master.slaves] == [esi.identity] * 2
            finally:
                master.close()
        report = stop(slaves, signal.SIGINT)
    assert "slave 0 " in report and "slave 1 " in report, report


def two_joints(port: str) -> str:
    """A robot file listing its two joints out of line order, each with its own setpoint."""
    return f"""[robot]
name = "two"

[[joints]]
name = "upper"
bus = "ethercat:{port}"
slave = 1
reference = {{ kind = "setpoint", position = -0.5 }}

[[joints]]
name = "lower"
bus = "ethercat:{port}"
slave = 0
reference = {{ kind = "setpoint", position = -1.5 }}
"""


def end_position(report: str, name: str) -> float:
    """rad: where sim-bus's end report says the drive called `name` stopped."""
    return float(report.split(f"{name} ")[1].split(" at ")[1].split(" rad")[0])


@pytest.mark.parametrize("served_by", ["slaves", "robot file"])
@pytest.mark.real_time
def test_actuatord_runs_a_robot_of_two_joints_on_one_line_in_slave_order(link, tmp_path,
                                                                         served_by):
    """Each joint's setpoint must reach the drive at its own slave position (the end positions
    sim-bus reports say which went where), whether sim-bus serves `--slaves 2` or the same
    robot file's line (commissioned drives, named by joint)."""
    robot = tmp_path / "two.toml"
    robot.write_text(two_joints(link.master_port))
    line = tmp_path / "line.toml"
    line.write_text(two_joints(link.line_port))
    serve = ("--slaves", "2") if served_by == "slaves" else ("--robot", str(line))
    with sim_bus(link, *serve) as slaves:
        result = run(link, "actuatord", "--robot", str(robot), "--lockstep", "--duration", "2",
                     ZENOH)
        report = stop(slaves)
    assert result.returncode == 0, result.stderr
    assert f"2 joints of two on ethercat:{link.master_port} enabled" in result.stdout
    assert "2000 cycles, 0 missed" in result.stdout
    lower, upper = ("slave 0", "slave 1") if served_by == "slaves" else ("lower", "upper")
    assert end_position(report, lower) == pytest.approx(-1.5, abs=0.05), report
    assert end_position(report, upper) == pytest.approx(-0.5, abs=0.05), report


@pytest.mark.real_time
def test_no_slave_on_the_line_is_a_failed_job_naming_the_bus(link):
    result = run(link, "actuatord", "--bus", f"ethercat:{link.master_port}", "--lockstep", ZENOH)
    assert result.returncode == 1, result.stderr
    errors = error_lines(result.stderr)
    assert len(errors) == 1 and f"ethercat:{link.master_port}" in errors[0], result.stderr
    assert "no slave answers" in errors[0]


@pytest.mark.parametrize("module, args, named", [
    ("actuatord", ["--bus", "ethercat:ecm0", "--node-id", "3"], "--node-id"),
    ("recorder", ["--sinusoid", "--bus", "ethercat:ecm0", "--node-id", "2", "-o", "{out}"],
     "--node-id"),
    ("actuatord", ["--bus", "ethercat:ecm0", "-b", "1000000"], "-b"),
    ("actuatord", ["--bus", "ethercat:ecm0", "--can-log", "{tmp}/frames.log"], "--can-log"),
    ("actuatord", ["--bus", "ethercat:ecm0", "--esi", "{tmp}/missing.xml"], "--esi"),
    ("recorder", ["--sinusoid", "--bus", "ethercat:ecm0", "--esi", "{tmp}/not_esi.xml",
                  "-o", "{out}"], "--esi"),
    ("actuatord", ["--bus", "vcan0", "--slave", "1"], "--slave"),
    ("actuatord", ["--bus", "ethercat:ecm0", "--slave", "-1"], "--slave"),
    ("sim_bus", ["--bus", "ethercat:ecs0", "--slaves", "0"], "--slaves"),
    ("sim_bus", ["--bus", "vcan0", "--slaves", "2"], "--slaves"),
    ("sim_bus", ["--bus", "ethercat:ecs0", "--slaves", "2", "--inject-fault", "2:silent@1"],
     "--inject-fault"),
])
def test_bad_ethercat_options_are_refused_in_one_line(tmp_path, capsys, module, args, named):
    """Refused before any interface opens, so each command's `main` runs in this process
    (none of these touches a bus or needs the namespace)."""
    main = importlib.import_module(f"commands.{module}").main
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    root = logging.getLogger()
    logging_before = (root.handlers[:], root.level)
    (tmp_path / "not_esi.xml").write_text("<EtherCATInfo><Vendor/></EtherCATInfo>")
    output = tmp_path / "out.mcap"
    args = [a.format(out=output, tmp=tmp_path) for a in args]
    try:
        code = main([*args, ZENOH] if module != "sim_bus" else args)
    except SystemExit as exc:  # argparse's refusals
        code = exc.code
    finally:  # a command sets up its process: give this one back as it was
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
        root.handlers[:], level = logging_before
        root.setLevel(level)
    stderr = capsys.readouterr().err
    assert code == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and named in lines[0], stderr
    assert not output.exists()
