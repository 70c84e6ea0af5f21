"""Masters die and others take over, on a loaded joint: every loss is caught whatever an
earlier master configured, the drive stops on its own (no SYNC or frame from anyone), and the
next master gets a drive that holds the joint with the current it commands, or is refused in
one line with the joint left held (issue 28, items 1-4).

EtherCAT: a line of one virtual slave in its own process on a veth (root); a master 'dies' by
closing its socket without a word, as a SIGKILL leaves the line. CAN: the virtual drive in its
own process over udp_multicast, masters killed with SIGKILL."""

import contextlib
import signal
import socket
import subprocess
import sys
import time

import pysoem
import pytest

from driver.canopen_drive import CanOpenDrive
from driver.clock import clock_for
from driver.ethercat_drive import JointOnLine, open_ethercat_drives
from driver.interface import DriveError, SampleLost
from model import dynamics
from model.parameters import Payload, load_model
from protocol import cia301, objects
from protocol import ethercat as ec
from protocol.cia402 import State, state_from_statusword
from sim_bus.ethercat.netns import SlaveProcess
from tests.conftest import as_a_real_time_master, udp_bus_spec, virtual_drive_process, wait_for
from tests.test_master_loss import Observer

MODEL = load_model()
HEAVY = Payload(20.0, 0.0, 0.05)  # the adversarial run's payload: 4x the elbow's own gravity
PACKED = MODEL.parameters.with_payload(HEAVY).packed()
HOLD_AT = -1.0  # rad, 1 rad from where the loaded joint hangs
STIFFNESS, DAMPING = 60.0, 6.0  # N.m/rad, N.m.s/rad: a plain holding PD beside gravity
STOPPED_WITHIN = 1.0  # s from the master's death to a drive at rest in switch on disabled

pytestmark = pytest.mark.subprocess


def holding_current(position: float, velocity: float) -> float:
    """Gravity compensation plus a PD towards HOLD_AT, in motor current (A)."""
    torque = (float(dynamics.gravity_torque(position, PACKED))
              + STIFFNESS * (HOLD_AT - position) - DAMPING * velocity)
    limit = MODEL.limits.current_max
    return max(-limit, min(limit, torque / MODEL.parameters.drive_gain))


def hold(drive, cycles: int, period: float | None = None) -> list[tuple[float, float, float]]:
    """Run the holding loop; (position, commanded current, measured current) per cycle; with
    a `period`, in real time at the master's priority."""
    with as_a_real_time_master() if period else contextlib.nullcontext():
        return _hold(drive, cycles, period)


def _hold(drive, cycles: int, period: float | None) -> list[tuple[float, float, float]]:
    out = []
    for _ in range(cycles):
        try:
            sample = drive.sync()
        except SampleLost:  # as the loop takes one: a cycle skipped, the command held
            continue
        current = holding_current(sample.position, sample.velocity)
        drive.command_current(current)
        out.append((sample.position, current, sample.motor_current))
        if period:
            time.sleep(period)
    return out


def assert_holds(trace: list[tuple[float, float, float]]) -> None:
    """The joint reached HOLD_AT and stays, and the drive makes the current it is asked for
    (a drive that applies nothing lets the loaded joint fall through its limit)."""
    settled = trace[len(trace) // 2:]
    assert all(abs(position - HOLD_AT) < 0.05 for position, _, _ in settled), settled[-1]
    for (_, commanded, _), (_, _, measured) in zip(settled, settled[1:], strict=False):
        assert abs(measured - commanded) < 0.3, (commanded, measured)  # sensor noise ~0.05 A


# --- EtherCAT ------------------------------------------------------------------------------

def joint() -> JointOnLine:
    return JointOnLine(0, MODEL.limits.velocity_max, MODEL.parameters.drive_gain)


def die(drive) -> None:
    """The master process dies: its socket closes, no INIT, no disable, no more frames."""
    drive.transport.line.master.close()


def al_status_of_line(interface: str) -> tuple[int, int]:
    """(AL status, AL status code) of the line's slaves as they are, read with one broadcast
    read (BRD of 0x0130..0x0135) on a raw socket: no scan, no state request, nothing that
    changes what the last master left."""
    with socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ec.ETHERTYPE)) as sock:
        sock.bind((interface, ec.ETHERTYPE))
        sock.settimeout(0.5)
        sock.send(ec.encode_frame([(ec.Command.BRD, 0x5A, ec.REG_AL_STATUS << 16,
                                    bytes(6))]))
        while True:
            frame = sock.recv(2048)
            spans = ec.datagram_spans(frame)
            if spans and frame[spans[0][1] + 1] == 0x5A and frame[6] & 0x02:
                data, wkc = ec.datagram_result(frame, spans[0])
                assert wkc == 1, wkc
                return (int.from_bytes(data[0:2], "little"),
                        int.from_bytes(data[4:6], "little"))


def drive_state_of_line(interface: str) -> tuple[State, float]:
    """(drive state, joint position) by CoE after a SOEM scan, as an engineer's tool reads
    them (the scan requests INIT: it changes the line, so it comes last)."""
    master = pysoem.Master()
    master.open(interface)
    try:
        assert master.config_init() == 1
        slave = master.slaves[0]
        statusword = int.from_bytes(slave.sdo_read(objects.STATUSWORD, 0), "little")
        increments = int.from_bytes(slave.sdo_read(objects.POSITION_ACTUAL, 0), "little",
                                    signed=True)
        return state_from_statusword(statusword), objects.increments_to_position(increments)
    finally:
        master.close()


@pytest.mark.real_time
def test_ethercat_every_lost_master_stops_the_drive_and_the_next_one_holds_the_load(link):
    with SlaveProcess(link, 1, MODEL, HEAVY) as line, link.entered():
        # a lock-step master switches the slave's watchdog off and ends as it should
        [drive] = open_ethercat_drives(link.master_port, [joint()], clock=clock_for(True))
        drive.start()
        hold(drive, 20)
        drive.close()
        for attempt in range(3):
            # a real-time master holds the joint with the drive's own current, then dies
            [drive] = open_ethercat_drives(link.master_port, [joint()], clock=clock_for(False))
            drive.start()
            assert_holds(hold(drive, 1500, period=0.0005))
            die(drive)
            time.sleep(STOPPED_WITHIN)
            al_status, code = al_status_of_line(link.master_port)
            # caught by the watchdog the lock-step master had switched off, every time (the
            # drive used to react to its first lost master only) ...
            assert al_status == ec.AlState.SAFE_OP | ec.AL_ERROR, (attempt, hex(al_status))
            assert code == ec.AL_SM_WATCHDOG, (attempt, hex(code))
            # ... and stopped on its own: no frame came since
            state, position = drive_state_of_line(link.master_port)
            assert state is State.SWITCH_ON_DISABLED, (attempt, state)
            assert abs(position - HOLD_AT) < 0.1, (attempt, position)  # the brake holds it
        [report] = line.report()
    assert report["brake_engaged"] and report["state"] == "SWITCH_ON_DISABLED"
    assert "watchdog" in report["master_loss"]


@pytest.mark.real_time
def test_ethercat_a_master_killed_in_lockstep_leaves_nothing_enabled_to_the_next(link):
    """No watchdog watches a lock-step line: the next master's scan (to INIT) is what the
    slave reacts to, as to a lost master, and the master disables whatever is left."""
    with SlaveProcess(link, 1, MODEL, HEAVY), link.entered():
        [drive] = open_ethercat_drives(link.master_port, [joint()], clock=clock_for(True))
        drive.start()
        hold(drive, 20)
        die(drive)
        [drive] = open_ethercat_drives(link.master_port, [joint()], clock=clock_for(False))
        try:
            drive.transport.boot(5.0)
            assert drive.state() is State.SWITCH_ON_DISABLED
            drive.start()
            # what this master enables applies this master's commands
            assert_holds(hold(drive, 1500, period=0.0005))
        finally:
            drive.close()


# --- CAN -----------------------------------------------------------------------------------

def start_actuatord(bus: str, *extra: str) -> subprocess.Popen:
    """actuatord holding the joint at HOLD_AT, once it says its drive is enabled."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "commands.actuatord", "--bus", bus, "--no-multicast-scouting",
         "--reference", f'{{"kind": "setpoint", "position": {HOLD_AT}}}', *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    assert "enabled" in line, f"actuatord did not start: {line!r} {proc.stderr.read()}"
    return proc


@pytest.mark.real_time
def test_can_a_drive_whose_master_died_stops_on_its_own_and_the_next_master_takes_it():
    bus = udp_bus_spec()
    payload = ("--payload-mass", "20", "--payload-position", "0,0.05")
    with virtual_drive_process(bus, 2, *payload):
        observer = Observer(bus)
        try:
            master = start_actuatord(bus, *payload)
            try:
                assert wait_for(lambda: len(observer.samples) > 300, 10.0)
                master.send_signal(signal.SIGKILL)
                dead_at = time.monotonic()
            finally:
                master.wait(10)
            # nobody sends a SYNC from here on: the drive's own time ends its quick stop
            assert wait_for(lambda: observer.state() is State.SWITCH_ON_DISABLED,
                              STOPPED_WITHIN), observer.state()
            assert time.monotonic() - dead_at < STOPPED_WITHIN + 0.5
            assert any(code == cia301.EMCY_HEARTBEAT for _, code in observer.emcys)
            held = observer.position()
            time.sleep(0.3)
            assert abs(observer.position() - held) < 0.01  # the brake holds the load
        finally:
            observer.close()
        # the next master is not refused: it resets the drive and drives it
        drive = CanOpenDrive.open(bus, 2, velocity_limit=MODEL.limits.velocity_max,
                                  drive_gain=MODEL.parameters.drive_gain, response_timeout=0.5)
        try:
            drive.start()
            trace = hold(drive, 1500, period=0.0005)
            assert_holds(trace)
        finally:
            drive.close()


@pytest.mark.real_time
def test_can_a_quick_stopping_drive_is_taken_over_not_refused():
    """A drive still in quick stop active (its master just died, the motor still turning)
    with no one cycling it is safe to take: the newcomer resets it rather than refusing."""
    bus = udp_bus_spec()
    with virtual_drive_process(bus, 2) as proc:
        drive = CanOpenDrive.open(bus, 2, velocity_limit=MODEL.limits.velocity_max,
                                  drive_gain=MODEL.parameters.drive_gain, response_timeout=0.5)
        try:
            drive.start()
            hold(drive, 100)
            drive.quick_stop()
            assert drive.state() in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
            drive.transport.health.close()  # the drive no longer hears from this master
        finally:
            drive.transport.close()
        assert proc.poll() is None
        other = CanOpenDrive.open(bus, 2, velocity_limit=MODEL.limits.velocity_max,
                                  drive_gain=MODEL.parameters.drive_gain, response_timeout=0.5)
        try:
            other.transport.boot(5.0)
            assert other.state() is State.SWITCH_ON_DISABLED
        except DriveError as exc:
            pytest.fail(f"refused: {exc}")
        finally:
            other.close()


@pytest.mark.real_time
def test_can_a_second_master_is_refused_and_the_first_runs_on_untouched():
    bus = udp_bus_spec()
    with virtual_drive_process(bus, 2):
        first = start_actuatord(bus)  # runs until stopped
        try:
            second = subprocess.run(
                [sys.executable, "-m", "commands.actuatord", "--bus", bus,
                 "--no-multicast-scouting", "--duration", "1"],
                capture_output=True, text=True, timeout=120)
            assert first.poll() is None, first.communicate()  # still running
            first.send_signal(signal.SIGTERM)
            out, err = first.communicate(timeout=30)
        finally:
            if first.poll() is None:
                first.kill()
                first.wait(10)
    assert second.returncode == 1, second.stdout + second.stderr
    errors = [line for line in second.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and "another master is driving it" in errors[0], errors
    # the first ran on untouched until asked to stop
    assert first.returncode == 0, out + err
    assert "stop requested" in out and "drive failed" not in out, out
