"""What the EtherCAT master says when a slave misbehaves, start-up parameters, and the drives'
dictionary over EtherCAT: a refused state change and a slave that leaves OP mid-run are named
with the joint and the AL status code in words, the robot quick-stopped; a frame short of its
working counter names the slaves not in OP by their AL status (read on their own when the
line's group read comes back late), and those that answer no read as not answering; the robot
file's start-up parameters are checked, written in PRE-OP, read back, and refused in one line;
SOEM browses the dictionary by SDO Information.

In lock-step the line is linked in this process (`sim_bus.ethercat.linked`); over a veth
(root) the slaves run in their own process and SOEM (pysoem) is the master."""

import json
import os
import re
import shutil
import struct
import subprocess
import sys
import time

import numpy as np
import pysoem
import pytest

from driver.clock import DriveClock, clock_for
from driver.drive_group import DriveGroup, EthercatLine, JointFailure
from driver.ethercat_drive import JointOnLine, open_ethercat_drives
from driver.ethercat_master import (
    CONFIGURING_RETURN_TIMEOUT_US,
    LOST_FRAMES_IN_A_ROW,
    STATE_CHECK_FRAMES,
    STATE_READ_TRIES,
    LineLost,
)
from driver.interface import SAMPLE_MOTOR_CURRENT, SAMPLE_T, DriveError, SampleLost
from model.parameters import Payload, load_model
from protocol import eds_path, esi_path, objects
from protocol import ethercat as ec
from protocol.cia402 import State
from protocol.dictionary import load_dictionary
from protocol.esi import ethercat_dictionary, load_esi
from robot.description import RobotFileError, load_robot
from robot.wiring import open_robot
from sim_bus.embedded import make_device
from sim_bus.ethercat import dc
from sim_bus.ethercat.linked import LinkedMaster
from sim_bus.ethercat.netns import SlaveProcess
from sim_bus.ethercat.segment import Segment
from sim_bus.faults import Fault
from sim_bus.plant import SensorNoise
from tests.conftest import soem_waiting_us

MODEL = load_model()
ESI = load_esi(esi_path())
NAMES = ("hip_joint", "knee_joint", "ankle_joint")


class LinkedRobot:
    """Three joints on one linked EtherCAT line in lock-step, as `--sim` builds them (with
    `real_time`, the master on the wall clock, the slaves' watchdog `watchdog` s)."""

    def __init__(self, names=NAMES, sync: str = "free_run", real_time: bool = False,
                 watchdog: float | None = None):
        self.devices = [make_device(MODEL, Payload(), SensorNoise(seed=k), commissioned=True)
                        for k in range(len(names))]
        self.segment = Segment(self.devices)
        joints = [JointOnLine(k, MODEL.limits.velocity_max, MODEL.parameters.drive_gain,
                              current_max=MODEL.limits.current_max, name=name)
                  for k, name in enumerate(names)]
        drives = open_ethercat_drives("sim", joints, clock=clock_for(not real_time),
                                      response_timeout=1.0, watchdog=watchdog, sync=sync,
                                      open_master=lambda: LinkedMaster(
                                          self.segment, clock_for(sync == "dc")))
        for drive in drives:
            drive.transport.boot(5.0)
        self.group = DriveGroup(list(names), [EthercatLine("ethercat:sim",
                                                           list(zip(names, drives, strict=True)))])

    def run(self, cycles: int) -> tuple[int, JointFailure | None]:
        """Cycles with zero current until one fails: (cycles completed, the failure)."""
        for k in range(cycles):
            try:
                self.group.sync()
                self.group.command_currents(np.zeros(len(self.group)))
            except JointFailure as failure:
                return k, failure
        return cycles, None

    def close(self) -> None:
        self.group.close()


@pytest.fixture
def robot():
    made = LinkedRobot()
    yield made
    made.close()


def test_a_refused_state_change_names_the_joint_and_the_al_status_code(robot):
    """The knee's slave refuses SAFE-OP (its firmware finds its sync managers wrong): the
    start fails naming that joint and slave, with the AL status code in words, and no drive
    was enabled."""
    firmware = robot.segment.firmwares[1]
    firmware._start_process_data = lambda: ec.AL_INVALID_SM_CONFIGURATION
    with pytest.raises(JointFailure) as refused:
        robot.group.start()
    assert refused.value.joint == "knee_joint"
    assert ("SAFE_OP refused: slave 1 (knee_joint) in PRE_OP + ERROR, AL status code invalid "
            "sync manager configuration (0x0017)") in str(refused.value)
    assert "slave 0" not in str(refused.value) and "slave 2" not in str(refused.value)
    assert all(device.state is not State.OPERATION_ENABLED for device in robot.devices)


def test_a_line_enables_its_drives_together_through_the_process_data():
    """The enable sequence rides the line's frames, every drive stepped in the same ones (a
    faulted drive reset on the way): one joint or three take the same few frames of drive
    time, and no controlword goes by SDO (these slaves refuse it from SAFE-OP on, as drives
    in the field do). One drive after the other by SDO, the joints enabled first waited at
    zero torque for the others."""
    frames = {}
    for names in (NAMES[:1], NAMES):
        robot = LinkedRobot(names=names)
        try:
            robot.devices[-1].inject(Fault.OVERCURRENT_TRIP)
            assert robot.devices[-1].state is State.FAULT
            robot.group.start()
            assert [d.state for d in robot.devices] == [State.OPERATION_ENABLED] * len(names)
            frames[len(names)] = {d.cycle_count for d in robot.devices}
            assert robot.run(5) == (5, None)
        finally:
            robot.close()
    assert frames[1] == frames[3] and len(frames[3]) == 1  # every slave saw every frame
    assert frames[3].pop() <= 12


def test_every_drive_of_a_line_quick_stops_in_the_first_frame(robot):
    """A group stages every drive's quick stop before any drive writes its own: the first
    drive's frame stops them all, not one drive a frame."""
    robot.group.start()
    assert robot.run(5) == (5, None)
    for drive in robot.group.drives:
        drive.stage_quick_stop()
    frames = [device.cycle_count for device in robot.devices]
    robot.group.drives[0].write_quick_stop()  # its frame
    assert [device.cycle_count for device in robot.devices] == [n + 1 for n in frames]
    assert all(device.state in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
               for device in robot.devices)


def test_a_slave_leaving_op_mid_run_is_named_and_every_drive_quick_stops(robot):
    """The ankle's slave drops to SAFE-OP + ERROR in the run's 30th cycle (its drive reacts
    as to a lost master, EMCY 0xA000): the cycle that meets it names the ankle with AL status
    code 0x001A rather than the emergency, and the group quick-stops every drive."""
    robot.group.start()  # its enable sequence's frames are drive time too
    ankle = robot.devices[2]
    ankle.schedule(Fault.LEAVES_OP, (ankle.cycle_count + 30) * 1e-3)
    completed, failure = robot.run(100)
    assert failure is not None and failure.joint == "ankle_joint"
    assert isinstance(failure.cause, LineLost)
    text = str(failure)
    assert ("slave 2 (ankle_joint) in SAFE_OP + ERROR, AL status code synchronization error "
            "(0x001A)") in text
    assert "slave 0" not in text and "slave 1" not in text
    # found in the very cycle whose frame the slave left OP in: no cycle ran after it
    [(fired, _)] = robot.devices[2].injected
    assert robot.devices[2].cycle_count == fired
    assert completed == robot.group.segments[0]._line.frames - 1
    robot.group.quick_stop_all()
    assert all(device.state in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
               for device in robot.devices)


def test_a_slave_out_of_op_with_a_quiet_drive_is_found_by_the_state_check(robot):
    """A slave that leaves OP while its drive is disabled raises no emergency and keeps the
    working counter whole (the ESC still moves its process data): the master's read of
    every AL status, every STATE_CHECK_FRAMES cycles, names it."""
    for drive in robot.group.drives:
        drive.configure()  # process data running, drives left disabled
    robot.group.segments[0].started()
    completed, failure = robot.run(5)
    assert failure is None
    robot.segment.firmwares[0].leave_op_on_error(ec.AL_SYNCHRONIZATION_ERROR)
    completed, failure = robot.run(3 * STATE_CHECK_FRAMES)
    assert failure is not None and failure.joint == "hip_joint"
    assert "left OP by cycle 10" in str(failure)
    assert "AL status code synchronization error (0x001A)" in str(failure)
    assert completed == STATE_CHECK_FRAMES - 5 - 1


def test_a_slave_out_of_op_whose_position_jumps_is_named_by_its_al_status(robot):
    """The knee's slave loses its sync and, in the same cycle, its position sample jumps
    (an encoder glitch the guard catches): the cycle names the slave and its AL status code,
    read as the guard fires, not a glitch, long before the periodic state check; a jump of
    a slave still in OP stays a glitch."""
    for drive in robot.group.drives:
        drive.configure()  # process data running, drives left disabled
    robot.group.segments[0].started()
    completed, failure = robot.run(3)
    assert failure is None
    robot.segment.firmwares[1].leave_op_on_error(ec.AL_SYNCHRONIZATION_ERROR)
    robot.devices[1].inject(Fault.ENCODER_GLITCH)
    completed, failure = robot.run(STATE_CHECK_FRAMES)
    assert completed == 0 and failure is not None and failure.joint == "knee_joint"
    assert isinstance(failure.cause, LineLost), failure
    assert ("slave 1 (knee_joint) in SAFE_OP + ERROR, AL status code synchronization error "
            "(0x001A)") in str(failure)
    assert "jumped" not in str(failure)


def test_a_position_jump_of_a_slave_in_op_is_an_encoder_glitch(robot):
    for drive in robot.group.drives:
        drive.configure()
    robot.group.segments[0].started()
    assert robot.run(3) == (3, None)
    robot.devices[2].inject(Fault.ENCODER_GLITCH)
    completed, failure = robot.run(STATE_CHECK_FRAMES)
    assert completed == 0 and failure is not None and failure.joint == "ankle_joint"
    assert "jumped" in str(failure) and "AL status" not in str(failure)


def _group_read_answered_late(master) -> None:
    """The line's group read of AL states as SOEM's ecx_readstate leaves it when the answer to
    its frame comes after its 6 ms (a slave host busy stopping its drives): every slave at
    state 0, as if none had answered."""
    def read_state() -> int:
        for slave in master.slaves:
            slave.state = slave.al_status = 0
        return 0

    master.read_state = read_state


def test_a_short_working_counter_names_slaves_in_safe_op_by_their_al_status():
    """DC: the knee's slave misses its SYNC0 windows (its clock jumped onto its frames) and
    loses its sync (SAFE-OP + ERROR, 0x001A, its outputs refused: the frame's working counter
    short), and the line's group read of AL states comes back late: the master reads the
    slaves on their own and names the knee in SAFE-OP with its AL status code in words, not
    as a slave that did not answer. (The line's own cycle, so that the drive's emergency
    does not have the master read the states before the frame does.)"""
    robot = LinkedRobot(sync="dc")
    try:
        robot.group.start()
        assert robot.run(20) == (20, None)
        line = robot.group.segments[0]._line
        _group_read_answered_late(line.master)
        memory = robot.segment.escs[1].memory
        (offset,) = struct.unpack_from("<Q", memory, dc.REG_SYSTEM_TIME_OFFSET)
        period_ns = 1_000_000
        struct.pack_into("<Q", memory, dc.REG_SYSTEM_TIME_OFFSET,
                         (offset + period_ns // 2 - 10_000) % 2**64)
        with pytest.raises(LineLost) as failure:
            for _ in range(STATE_CHECK_FRAMES - 1):
                line.cycle()
    finally:
        robot.close()
    assert failure.value.positions == (1,)
    text = str(failure.value)
    assert "working counter 7, expected 9" in text
    assert ("slave 1 (knee_joint) in SAFE_OP + ERROR, AL status code synchronization error "
            "(0x001A)") in text
    assert "did not answer" not in text
    assert "slave 0" not in text and "slave 2" not in text


def test_a_slave_that_answers_no_read_of_its_own_is_named_as_not_answering(robot):
    """The ankle's slave goes silent (the frame's working counter short of its share) and
    the group read comes back late: the ankle answers none of the reads of the line's AL
    states nor one of its own and is named as not answering; the others, in OP, are not."""
    robot.group.start()
    assert robot.run(3) == (3, None)
    _group_read_answered_late(robot.group.segments[0]._line.master)
    robot.devices[2].inject(Fault.SILENT)
    completed, failure = robot.run(STATE_CHECK_FRAMES)
    assert failure is not None and failure.joint == "ankle_joint"
    text = str(failure)
    assert "working counter 6, expected 9" in text
    assert f"slave 2 (ankle_joint) did not answer (no answer to {STATE_READ_TRIES} reads of "\
           "the line's AL states nor to one of its own" in text
    assert "slave 0" not in text and "slave 1" not in text


@pytest.mark.parametrize("sync", ["free_run", "dc"])
def test_a_lost_frame_is_ridden_through_the_drives_holding_their_command(sync):
    """A frame lost on its way back to the master (fault frame_lost: every slave took it):
    that cycle has no sample, SampleLost and no joint's failure; the next frame's sample is
    two periods on, the drives still enabled and running the command they held. Lost frames
    apart, each with good frames between, never add up to a failure."""
    robot = LinkedRobot(sync=sync)
    try:
        robot.group.start()
        line = robot.group.segments[0]._line
        assert robot.run(3) == (3, None)
        robot.group.command_currents(np.array([0.2, 0.0, -0.2]))
        before = robot.group.sync()
        robot.devices[1].inject(Fault.FRAME_LOST)
        with pytest.raises(SampleLost, match=r"frame of cycle \d+ did not come back within "
                                             r"1000 ms \(1 in a row"):
            robot.group.sync()
        after = robot.group.sync()
        assert after[0, SAMPLE_T] - before[0, SAMPLE_T] == pytest.approx(2e-3)
        assert [round(c, 1) for c in after[:, SAMPLE_MOTOR_CURRENT]] == [0.2, 0.0, -0.2]
        assert all(device.state is State.OPERATION_ENABLED for device in robot.devices)
        for _ in range(4):
            robot.devices[0].inject(Fault.FRAME_LOST)
            with pytest.raises(SampleLost, match=r"\(1 in a row"):
                robot.group.sync()
            assert robot.run(2) == (2, None)
        assert line.lost_frames == 5 and line.failure is None
    finally:
        robot.close()


def test_a_lost_frame_has_no_sample_for_any_joint_of_the_line(robot):
    """Joints on one line exchanged one by one (the path of a line whose slaves do not share
    a layout): the joint whose exchange sent the lost frame and every other joint of that
    cycle get SampleLost, none a stale sample; the next cycle's frame serves them all."""
    robot.group.start()
    first, second = (drive.transport for drive in robot.group.drives[:2])
    line = first.line
    frames = line.frames
    robot.devices[0].inject(Fault.FRAME_LOST)
    for transport in (first, second):
        with pytest.raises(SampleLost):
            transport.exchange()
    first.exchange()
    second.exchange()
    assert line.frames == frames + 2 and line.lost_frames == 1


def test_frames_lost_past_what_the_drives_forgive_fail_the_line(robot):
    """LOST_FRAMES_IN_A_ROW frames lost in a row are ridden through; the next lost fails the
    line (no frame came back, every slave in the cycle named as lost), a failure of the
    joint on the first slave, as any broken line is."""
    robot.group.start()
    assert robot.run(3) == (3, None)
    for lost in range(1, LOST_FRAMES_IN_A_ROW + 1):
        robot.devices[2].inject(Fault.FRAME_LOST)
        with pytest.raises(SampleLost, match=rf"\({lost} in a row"):
            robot.group.sync()
    robot.devices[2].inject(Fault.FRAME_LOST)
    completed, failure = robot.run(1)
    assert completed == 0 and failure is not None and failure.joint == "hip_joint"
    assert isinstance(failure.cause, LineLost)
    assert (f"no frame came back within 1000 ms (cycle 6, {LOST_FRAMES_IN_A_ROW + 1} in a "
            "row): slave 0 (hip_joint), slave 1 (knee_joint), slave 2 (ankle_joint) lost"
            ) in str(failure)


def test_each_fault_on_a_frames_answer_acts_on_one_answer_and_then_none():
    """A slave's fault on the line's answer (TPDO_LATE: held, TPDO_TWICE: sent twice,
    FRAME_LOST: lost) acts on the next answer it can act on and on no other; a line none of
    whose slaves has one looks at them only through the flag they share (`FrameFaults`)."""
    devices = [make_device(load_model(), Payload(), SensorNoise()) for _ in range(3)]
    segment = Segment(devices)
    assert not segment.frame_faults.pending
    assert segment.injected_timing() == (0.0, False) and not segment.frame_lost()
    devices[2].inject(Fault.TPDO_TWICE)
    devices[0].inject(Fault.TPDO_LATE)
    assert segment.frame_faults.pending
    delay, twice = segment.injected_timing()
    assert delay > 0 and twice
    assert segment.injected_timing() == (0.0, False) and not segment.frame_faults.pending
    # a loss waits for a frame with process data: another frame's answer (no logical
    # datagram in it) passes
    devices[1].inject(Fault.FRAME_LOST)
    other = bytearray(64)
    assert not segment.frame_lost(other, len(other))
    assert segment.injected_timing() == (0.0, False) and segment.frame_faults.pending
    devices[1].inject(Fault.TPDO_TWICE)
    assert segment.frame_lost()  # the cycle's frame, lost: its twice waits for the next
    assert segment.frame_faults.pending and not segment.frame_lost()
    assert segment.injected_timing() == (0.0, True)
    assert not segment.frame_faults.pending


@pytest.mark.real_time
def test_in_real_time_frames_lost_are_ridden_through_until_the_drives_watchdog(caplog):
    """On the wall clock the line rides through frames lost in a row for as long as its
    drives hold without one (their process data watchdog since the last whole frame, here
    300 ms), more than the drive-time rule's LOST_FRAMES_IN_A_ROW: a host that holds the
    line's process for a few ms costs cycles, not the robot. One warning for a run of lost
    frames and one when they come back. Frames that stay lost fail the line once the
    watchdog has passed, every slave named, and then no CoE access waits for an answer."""
    robot = LinkedRobot(real_time=True, watchdog=0.3)
    try:
        robot.group.start()
        assert robot.run(3) == (3, None)
        line = robot.group.segments[0]._line
        caplog.set_level("WARNING", logger="driver.ethercat_master")
        in_a_row = LOST_FRAMES_IN_A_ROW + 3
        for lost in range(1, in_a_row + 1):
            robot.devices[0].inject(Fault.FRAME_LOST)
            with pytest.raises(SampleLost, match=rf"\({lost} in a row; \d+ ms without a whole "
                                                 r"frame; the line fails at the drives' "
                                                 r"watchdog, 300 ms\)"):
                robot.group.sync()
            time.sleep(1e-3)
        assert robot.run(2) == (2, None)
        assert line.lost_frames == in_a_row and line.failure is None
        warnings = [r.getMessage() for r in caplog.records]
        assert len(warnings) == 2 and "(1 in a row" in warnings[0]
        assert f"frames back after {in_a_row} lost in a row" in warnings[1]
        while True:  # now they stay lost
            robot.devices[0].inject(Fault.FRAME_LOST)
            try:
                robot.group.sync()
            except SampleLost:
                time.sleep(1e-3)
                continue
            except JointFailure as exc:
                failure = exc
            break
        assert isinstance(failure.cause, LineLost)
        silence = re.search(r"in a row, (\d+) ms without a whole frame, past the drives' "
                            r"watchdog\): slave 0 \(hip_joint\), slave 1 \(knee_joint\), "
                            r"slave 2 \(ankle_joint\) lost", str(failure))
        assert silence is not None, str(failure)
        assert int(silence.group(1)) >= 300
        # nothing answers: a CoE access (the quick stop's, the close's) fails at once, not
        # after its mailbox timeouts slave by slave (these slaves would still answer one)
        transport = robot.group.drives[2].transport
        with pytest.raises(DriveError, match="not tried: nothing on the line answers"):
            transport.write(objects.CONTROLWORD, 0, 6)
        with pytest.raises(DriveError, match="not tried: nothing on the line answers"):
            transport.read(objects.MAX_CURRENT)
    finally:
        robot.close()


def _robot_file(tmp_path, names=NAMES) -> str:
    text = '[robot]\nname = "leg"\nperiod_us = 1000\n'
    for position, name in enumerate(names):
        text += f'\n[[joints]]\nname = "{name}"\nbus = "ethercat:eth9"\nslave = {position}\n'
    path = tmp_path / "leg.toml"
    path.write_text(text)
    return str(path)


@pytest.mark.subprocess
def test_actuatord_quick_stops_the_robot_and_names_the_joint_that_left_op(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep",
         "--no-multicast-scouting", "--robot", _robot_file(tmp_path), "--duration", "1",
         "--inject-fault", "knee_joint:leaves_op@0.5"],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 1, result.stderr
    # one error line says it all (the drive's own reaction, EMCY 0xA000, is logged before it)
    [error] = [line for line in result.stderr.splitlines() if "0x001A" in line
               and line.startswith("actuatord: error:")]
    assert "slave 1 (knee_joint) in SAFE_OP + ERROR, AL status code synchronization error "\
           "(0x001A)" in error
    assert "drive failed: joint knee_joint:" in result.stdout
    stop_line = next(line for line in result.stdout.splitlines() if "quick stop:" in line)
    assert all(name in stop_line for name in NAMES)
    assert "operation enabled" not in stop_line


@pytest.mark.subprocess
def test_actuatord_rides_through_a_lost_frame(tmp_path):
    """A frame lost mid-run (lock-step, the line linked in the process): the run goes on to
    its end, the cycle without a sample missed as a late sample and counted lost, said in
    one warning line; no joint failed."""
    report = tmp_path / "report.json"
    result = subprocess.run(
        [sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep",
         "--no-multicast-scouting", "--robot", _robot_file(tmp_path), "--duration", "1",
         "--inject-fault", "knee_joint:frame_lost@0.5", "--report", str(report)],
        capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    figures = json.loads(report.read_text())
    assert figures["lost_samples"] == 1 and figures["missed"] == 1
    assert figures["missed_by_cause"]["late sample"] == 1
    assert figures["cycles"] == 999 and figures["fallbacks"] == 0
    # the start's phases, the drives' side of it: configured, then enabled together
    assert figures["configure_us"] > figures["enable_us"] > 0
    [warning] = [line for line in result.stderr.splitlines() if "did not come back" in line]
    assert "EtherCAT eth9: the frame of cycle" in warning and "(1 in a row" in warning
    assert "(1 samples lost); ran 1.0 s" in result.stdout


@pytest.mark.root
@pytest.mark.subprocess
@pytest.mark.real_time
def test_soem_names_the_slave_that_vanished_and_the_one_that_left_op(link):
    """Over a veth with SOEM: a slave made silent mid-run (fault 2 written to 0x2010) is named
    as not answering by the frame that misses it; on a fresh line a slave that leaves OP is
    named with its AL status code by the state check, its working counter whole."""
    joints = [JointOnLine(k, MODEL.limits.velocity_max, MODEL.parameters.drive_gain,
                          name=name) for k, name in enumerate(NAMES[:2])]
    for fault, expected in (
            (Fault.SILENT, "slave 1 (knee_joint) did not answer"),
            (Fault.LEAVES_OP, "slave 1 (knee_joint) in SAFE_OP + ERROR, AL status code "
                              "synchronization error (0x001A)")):
        with SlaveProcess(link, 2, MODEL), link.entered():
            drives = open_ethercat_drives(link.master_port, joints, clock=clock_for(True),
                                          response_timeout=0.2)
            on_line = list(zip(NAMES[:2], drives, strict=True))
            group = DriveGroup(list(NAMES[:2]), [EthercatLine("ethercat:veth", on_line)])
            try:
                group.start()
                for _ in range(3):
                    group.sync()
                    group.command_currents(np.zeros(2))
                if fault is Fault.SILENT:  # gone before it could answer the write
                    with pytest.raises(DriveError, match="0x2010"):
                        drives[1].transport.write(objects.FAULT_INJECTION, 0, fault.value)
                else:
                    drives[1].transport.write(objects.FAULT_INJECTION, 0, fault.value)
                with pytest.raises(JointFailure) as failed:
                    for _ in range(2 * STATE_CHECK_FRAMES):
                        group.sync()
                        group.command_currents(np.zeros(2))
                assert failed.value.joint == "knee_joint"
                assert expected in str(failed.value)
                assert "slave 0" not in str(failed.value)
            finally:
                group.close()


@pytest.mark.root
@pytest.mark.subprocess
@pytest.mark.real_time
def test_soem_rides_through_a_frame_the_line_lost(link):
    """Over a veth with SOEM: the slaves' process drops its answer to one process data frame
    (fault 11 written to 0x2010; the SDO write's own frames pass): SOEM's receive gives
    EC_NOFRAME after the response timeout, that cycle raises SampleLost, and the cycles after
    it run on SOEM's next frames (their answers matched by index, the late one never taken),
    no joint failed."""
    joints = [JointOnLine(k, MODEL.limits.velocity_max, MODEL.parameters.drive_gain,
                          name=name) for k, name in enumerate(NAMES[:2])]
    with SlaveProcess(link, 2, MODEL), link.entered():
        drives = open_ethercat_drives(link.master_port, joints, clock=clock_for(True),
                                      response_timeout=0.2)
        group = DriveGroup(list(NAMES[:2]),
                           [EthercatLine("ethercat:veth", list(zip(NAMES[:2], drives,
                                                                   strict=True)))])
        try:
            group.start()
            for _ in range(3):
                group.sync()
                group.command_currents(np.zeros(2))
            drives[1].transport.write(objects.FAULT_INJECTION, 0, Fault.FRAME_LOST.value)
            with pytest.raises(SampleLost, match=r"did not come back within 200 ms"):
                group.sync()
            times = []
            for _ in range(5):
                times.append(group.sync()[0, SAMPLE_T])
                group.command_currents(np.zeros(2))
            assert np.diff(times) == pytest.approx(1e-3)
            line = drives[0].transport.line
            assert line.lost_frames == 1 and line.failure is None
        finally:
            group.close()


# --- start-up parameters ------------------------------------------------------------------------

STARTUP_ROBOT = """
[robot]
name = "leg"

[drive_types.knee]
sdo = [{ index = 0x6073, value = 1200 }, { index = 0x6072, value = 700 }]

[[joints]]
name = "hip_joint"
bus = "ethercat:eth9"
slave = 0
sdo = [{ index = 0x6072, subindex = 0, value = 800 }]

[[joints]]
name = "knee_joint"
bus = "ethercat:eth9"
slave = 1
drive_type = "knee"
sdo = [{ index = 0x6072, value = 600 }]

[[joints]]
name = "ankle_joint"
bus = "vcan9"
node_id = 3
drive_type = "knee"
"""


def _startup_robot(tmp_path, text: str = STARTUP_ROBOT):
    path = tmp_path / "leg.toml"
    path.write_text(text)
    return path


def test_start_up_parameters_per_drive_type_and_joint_are_parsed_in_order(tmp_path):
    robot = load_robot(_startup_robot(tmp_path))
    startup = {joint.name: [tuple(p) for p in joint.startup] for joint in robot.joints}
    assert startup == {
        "hip_joint": [(objects.MAX_TORQUE, 0, 800)],
        # the type's first, the joint's own replacing the type's for the same object
        "knee_joint": [(objects.MAX_CURRENT, 0, 1200), (objects.MAX_TORQUE, 0, 600)],
        "ankle_joint": [(objects.MAX_CURRENT, 0, 1200), (objects.MAX_TORQUE, 0, 700)]}


@pytest.mark.parametrize("entry, message", [
    ("{ index = 0x9999, value = 1 }", "0x9999:00 is not in the drive's dictionary"),
    ("{ index = 0x6041, value = 1 }", "0x6041:00 (Statusword) is ro, not writable"),
    ("{ index = 0x6072, value = 70000 }", "70000 is outside its data type's 0..65535"),
    ("{ index = 0x6072, value = 1.5 }", "expected an integer, got 1.5"),
    ("{ index = 0x6060, value = 10 }", "the master sets the mode itself"),
    ("{ index = 0x1A00, subindex = 1, value = 0 }", "the master sets the PDO communication"),
    ("{ index = 0x6072, subindex = 256, value = 1 }", "subindex: expected an integer 0..255"),
    ("{ index = 0x6072 }", "sdo[0].value: missing"),
    ("{ index = 0x6072, value = 1, sub = 0 }", "sdo[0].sub: unknown key"),
])
def test_a_malformed_start_up_parameter_is_refused_naming_joint_and_object(tmp_path, entry,
                                                                         message):
    text = STARTUP_ROBOT.replace("{ index = 0x6072, subindex = 0, value = 800 }", entry)
    with pytest.raises(RobotFileError) as refused:
        load_robot(_startup_robot(tmp_path, text))
    assert "joint 'hip_joint'.sdo[0]" in str(refused.value)
    assert message in str(refused.value)


def test_an_unknown_or_unused_drive_type_is_refused(tmp_path):
    with pytest.raises(RobotFileError, match=r"drive_type: 'wrist' is not in \[drive_types\]"):
        load_robot(_startup_robot(tmp_path, STARTUP_ROBOT.replace('"knee"\nsdo', '"wrist"\nsdo')))
    with pytest.raises(RobotFileError, match=r"\[drive_types.knee\]: no joint is of this type"):
        load_robot(_startup_robot(tmp_path, STARTUP_ROBOT.replace('drive_type = "knee"', "")))


def test_start_up_parameters_reach_ethercat_and_canopen_drives_before_the_scaling(tmp_path):
    """Written in PRE-OP (PRE-OPERATIONAL on the CAN joint), read back, and in force when
    the master reads the drive's limits: the knee type's 120 % max current is the current
    limit the master plans with."""
    robot = load_robot(_startup_robot(tmp_path))
    connection = open_robot(robot, sim=True, clock=DriveClock(), seed=0, period=1e-3,
                            response_timeout=1.0)
    try:
        connection.group.start()
        devices = connection.devices
        assert devices["hip_joint"].read(objects.MAX_TORQUE, 0) == 800
        assert devices["knee_joint"].read(objects.MAX_TORQUE, 0) == 600
        for name in ("knee_joint", "ankle_joint"):
            assert devices[name].read(objects.MAX_CURRENT, 0) == 1200
        hip, knee, ankle = connection.group.drives
        assert knee.current_limit == pytest.approx(1.2 * hip.current_limit)
        assert ankle.current_limit == pytest.approx(1.2 * hip.current_limit)
    finally:
        connection.close()


@pytest.mark.parametrize("joint", ["hip_joint", "ankle_joint"])
def test_a_start_up_parameter_the_drive_refuses_stops_the_start_in_one_line(tmp_path, joint):
    """Fault code 99 fits 0x2010's UNSIGNED8 (the file is well-formed) but the drive knows no
    such fault: its SDO abort ends the start, naming joint, object and abort code in words,
    before any drive is enabled; over EtherCAT (hip) and CANopen (ankle) alike."""
    text = STARTUP_ROBOT.replace(f'name = "{joint}"\n', f'name = "{joint}"\n'
                                 'sdo = [{ index = 0x2010, value = 99 }]\n')
    text = text.replace('sdo = [{ index = 0x6072, subindex = 0, value = 800 }]\n', "")
    connection = open_robot(load_robot(_startup_robot(tmp_path, text)), sim=True,
                            clock=DriveClock(), seed=0, period=1e-3, response_timeout=1.0)
    try:
        with pytest.raises(JointFailure) as refused:
            connection.group.start()
        assert refused.value.joint == joint
        assert ("start-up parameter 0x2010:00 (Fault injection) = 99 refused by the drive: "
                "Value range of parameter exceeded (0x06090030)") in str(refused.value)
        assert all(device.state is not State.OPERATION_ENABLED
                   for device in connection.devices.values())
    finally:
        connection.close()


@pytest.mark.subprocess
def test_actuatord_exits_2_for_a_bad_start_up_parameter_and_1_for_a_refused_one(tmp_path):
    bad = STARTUP_ROBOT.replace("value = 800", "value = 70000")
    refused = STARTUP_ROBOT.replace("value = 800", "value = 99").replace(
        "index = 0x6072, subindex = 0", "index = 0x2010, subindex = 0")
    for text, code, words in ((bad, 2, "70000 is outside its data type's 0..65535"),
                              (refused, 1, "Value range of parameter exceeded (0x06090030)")):
        result = subprocess.run(
            [sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep",
             "--no-multicast-scouting", "--robot", str(_startup_robot(tmp_path, text)),
             "--duration", "0.1"], capture_output=True, text=True, timeout=300)
        assert result.returncode == code, result.stderr
        assert "hip_joint" in result.stderr and words in result.stderr


# --- the dictionary over EtherCAT (SDO Information) --------------------------------------------


@pytest.mark.root
@pytest.mark.subprocess
@pytest.mark.real_time
def test_soem_browses_the_drives_dictionary_by_sdo_information(link):
    """pysoem's `od` (SOEM's ecx_readODlist, ecx_readODdescription, ecx_readOE: an
    implementation nobody here wrote) lists every object the slave reaches by SDO, with the
    EDS's names and types, PDO-mappable where the ESI's PDOs carry them; the slave's SII says
    it offers the service."""
    assert ESI.coe_details & ec.COE_DETAILS_SDO_INFO  # what the SII's general category says
    dictionary = ethercat_dictionary(load_dictionary(eds_path()), ESI)
    with (soem_waiting_us(CONFIGURING_RETURN_TIMEOUT_US), SlaveProcess(link, 1, MODEL),
          link.entered()):
        master = pysoem.Master()
        master.open(link.master_port)
        try:
            assert master.config_init() == 1
            slave = master.slaves[0]
            browsed = {obj.index: obj for obj in slave.od}
            expected = {index for index in dictionary
                        if not 0x1400 <= index < 0x1600 and not 0x1800 <= index < 0x1A00}
            assert set(browsed) == expected | {ec.SM_COMMUNICATION_TYPE, ec.RXPDO_ASSIGN,
                                               ec.TXPDO_ASSIGN}
            for index in expected:
                obj, described = dictionary[index], browsed[index]
                assert described.name.decode() == obj.name, hex(index)
                if not hasattr(obj, "subindices"):  # a VAR: pysoem keeps its one entry on it
                    assert (described.object_code, described.data_type) == (
                        ec.OBJECT_CODE_VAR, obj.data_type), hex(index)
                    continue
                entries = [obj.subindices[k] for k in sorted(obj.subindices)]
                assert [e.name.decode() for e in described.entries] == [e.name for e in entries]
                assert [e.data_type for e in described.entries] == [
                    e.data_type for e in entries]
            statusword = browsed[objects.STATUSWORD]
            assert statusword.bit_length == 16
            assert statusword.obj_access == ec.ENTRY_ACCESS_READ | ec.ENTRY_ACCESS_TXPDO
            torque = browsed[objects.TARGET_TORQUE]
            assert torque.obj_access & ec.ENTRY_ACCESS_RXPDO
            assign = browsed[ec.TXPDO_ASSIGN]
            assert (assign.name, assign.object_code) == (b"TxPDO assign", ec.OBJECT_CODE_ARRAY)
            # the same values by plain SDO: the browse left the mailbox in step
            assert struct.unpack("<H", slave.sdo_read(ec.TXPDO_ASSIGN, 1)) == (0x1A00,)
        finally:
            master.close()


def _slaveinfo_builds() -> list[str]:
    """SOEM's own slaveinfo sample programs to run: $SOEM_SLAVEINFO (paths separated by
    os.pathsep: e.g. a v1.4 and a v2.0 build), else one on PATH."""
    paths = [p for p in os.environ.get("SOEM_SLAVEINFO", "").split(os.pathsep) if p]
    found = shutil.which("slaveinfo")
    return paths or ([found] if found else [])


@pytest.mark.root
@pytest.mark.subprocess
@pytest.mark.parametrize("option", ["-sdo", "-map"])
@pytest.mark.real_time
def test_soems_slaveinfo_browses_and_maps_the_slave(link, option):
    """SOEM's C sample itself: `-sdo` (SDO Information for every object; v1.4 used to get
    'service not supported' for each) and `-map` (entry descriptions of the mapped objects;
    v2.0 used to segfault in ecx_mbxreceive after the slave's mailbox error reply)."""
    builds = _slaveinfo_builds()
    if not builds:
        pytest.skip("no SOEM slaveinfo build (set SOEM_SLAVEINFO to its path)")
    with SlaveProcess(link, 1, MODEL):
        for build in builds:
            result = subprocess.run(["ip", "netns", "exec", link.name, build, link.master_port,
                                     option], capture_output=True, text=True, timeout=120)
            assert result.returncode == 0, (build, result.returncode, result.stderr)
            assert "not supported" not in result.stdout and "no supported" not in result.stdout
            assert "Statusword" in result.stdout and "Target torque" in result.stdout, build
