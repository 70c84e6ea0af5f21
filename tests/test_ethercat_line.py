"""Virtual EtherCAT slaves and the pysoem master on a veth pair in a private network
namespace: bring-up as SOEM does it, CST process data, lock-step cycles, and the faults
(slave killed, state refused, master lost, emergencies, malformed frames)."""

import contextlib
import dataclasses
import os
import socket
import struct
import time

import pysoem
import pytest

from driver.clock import clock_for
from driver.drive_group import DriveGroup, EthercatLine
from driver.ethercat_drive import JointOnLine, open_ethercat_drives
from driver.ethercat_master import (
    CONFIGURING_RETURN_TIMEOUT_US,
    LOST_FRAMES_IN_A_ROW,
    _packet_sockets,
)
from driver.ethercat_transport import open_ethercat_transports
from driver.interface import (
    SAMPLE_MOTOR_CURRENT,
    DriveError,
    DriveFault,
    DriveLost,
    ProfileError,
    SampleLost,
)
from model.parameters import load_model
from protocol import esi_path, objects
from protocol import ethercat as ec
from protocol.dictionary import mapped_object, variable
from protocol.esi import load_esi
from sim_bus.ethercat.netns import SlaveProcess
from tests.conftest import soem_waiting_us

ESI = load_esi(esi_path())
MODEL = load_model()
CONTROLWORD_ENABLE = 0x0F


def joint(position: int) -> JointOnLine:
    return JointOnLine(position, MODEL.limits.velocity_max, MODEL.parameters.drive_gain)


def slaves(link, count):
    return SlaveProcess(link, count, MODEL)


def cst_profile(dictionary):
    obj = lambda index: mapped_object(variable(dictionary, index))  # noqa: E731
    return ((obj(objects.CONTROLWORD), obj(objects.TARGET_TORQUE)),
            (obj(objects.STATUSWORD), obj(objects.POSITION_ACTUAL), obj(objects.VELOCITY_ACTUAL),
             obj(objects.CURRENT_ACTUAL), obj(objects.JOINT_TORQUE_SENSOR)))


def bring_up(transports):
    for transport in transports:
        transport.boot(5.0)
        transport.write(objects.MODES_OF_OPERATION, 0, objects.MODE_CYCLIC_SYNC_TORQUE)
        transport.map_process_data(*cst_profile(transport.dictionary))
        transport.start(1e-3)


def enable(transport):
    for controlword in (0x06, 0x07, CONTROLWORD_ENABLE):
        transport.write(objects.CONTROLWORD, 0, controlword)


def close(transports):
    for transport in transports:
        transport.stop()
        transport.close()


@pytest.mark.real_time
def test_soem_finds_the_slaves_reads_their_sii_and_maps_the_cst_layout(link):
    with (soem_waiting_us(CONFIGURING_RETURN_TIMEOUT_US), slaves(link, 2),
          link.entered()):
        master = pysoem.Master()
        master.open(link.master_port)
        try:
            assert master.config_init() == 2
            for slave in master.slaves:
                assert (slave.man, slave.id, slave.rev) == ESI.identity
                assert slave.name == ESI.name
            assert master.state_check(pysoem.PREOP_STATE, 2_000_000) == pysoem.PREOP_STATE
            assert master.config_map() == 2 * (4 + 18)
            assert master.state_check(pysoem.SAFEOP_STATE, 2_000_000) == pysoem.SAFEOP_STATE
            slave = master.slaves[1]
            assert (len(slave.output), len(slave.input)) == (4, 18)
            assert struct.unpack("<H", slave.sdo_read(0x1C12, 1))[0] == 0x1600
            assert [struct.unpack("<I", slave.sdo_read(0x1A00, k))[0] for k in range(1, 7)] == [
                e.mapping_entry for e in ESI.txpdos[0].entries]
            master.state = pysoem.OP_STATE
            master.write_state()
            for _ in range(5):
                master.send_processdata()
                assert master.receive_processdata(100_000) == master.expected_wkc == 6
            assert master.state_check(pysoem.OP_STATE, 2_000_000) == pysoem.OP_STATE
        finally:
            master.state = pysoem.INIT_STATE
            master.write_state()
            master.close()


@pytest.mark.real_time
def test_lockstep_drives_move_each_joint_the_commanded_way_one_frame_per_cycle(link):
    with slaves(link, 2) as line, link.entered():
        drives = open_ethercat_drives(link.master_port, [joint(0), joint(1)], clock=clock_for(True))
        try:
            for drive in drives:
                drive.start()
            assert drives[0].profile.mode == objects.MODE_CYCLIC_SYNC_TORQUE  # CST over ESI
            frames = drives[0].transport.line.frames
            start = [drive.sync().position for drive in drives]
            for _ in range(200):
                drives[0].command_current(0.5)
                drives[1].command_current(-0.5)
                samples = [drive.sync() for drive in drives]
            assert drives[0].transport.line.frames == frames + 201  # both joints, one frame
            # on drive time SOEM's sockets stay as it opened them: a wait for a frame sleeps
            sockets = _packet_sockets(link.master_port)
            assert sockets and all(os.get_blocking(fd) for fd in sockets)
        finally:
            for drive in drives:
                drive.close()
        report = line.report()
    assert samples[0].position > start[0] + 0.005  # rad
    assert samples[1].position < start[1] - 0.005
    assert samples[0].motor_current == pytest.approx(0.5, abs=0.05)
    # one frame a cycle for both; the disable on close goes by a frame too (the process data
    # carries the controlword), and slave 0 had left the cycle when drive 1 closed
    assert report[1]["cycles"] == report[0]["cycles"] + 1
    assert [r["state"] for r in report] == ["SWITCH_ON_DISABLED"] * 2  # closed cleanly
    assert not any(r["master_loss"] for r in report)


@pytest.mark.real_time
def test_a_line_is_one_segment_of_a_drive_group(link):
    """The robot's seam: three joints on one line, started in joint order (the line goes to
    OP with the last), one frame per group cycle, a quick stop for all."""
    names = ["shoulder", "elbow", "wrist"]
    with slaves(link, 3) as line, link.entered():
        drives = open_ethercat_drives(link.master_port, [joint(k) for k in range(3)],
                                      clock=clock_for(True))
        group = DriveGroup(names, [EthercatLine(f"ethercat:{link.master_port}",
                                                list(zip(names, drives, strict=True)))])
        try:
            group.start()
            frames = drives[0].transport.line.frames
            for _ in range(50):
                samples = group.sync()
                group.command_currents([0.2, 0.0, -0.2])
            assert drives[0].transport.line.frames == frames + 50
            assert [round(current, 1) for current in samples[:, SAMPLE_MOTOR_CURRENT]] == [
                0.2, 0.0, -0.2]
            states = group.quick_stop_all()
        finally:
            group.close()
        report = line.report()
    assert [name for name, _ in states] == names
    assert all(state in ("quick stop active", "switch on disabled") for _, state in states)
    assert [r["brake_engaged"] for r in report] == [True] * 3


@pytest.mark.real_time
def test_identity_other_than_the_esi_is_refused(link):
    other = dataclasses.replace(ESI, product_code=0x999)
    with slaves(link, 1), link.entered():
        [transport] = open_ethercat_transports(link.master_port, [0], esi=other)
        try:
            with pytest.raises(ProfileError, match=r"slave 0 .*product 0x00000402.* the ESI "
                                                   r"describes .*product 0x00000999"):
                transport.boot(0.3)
        finally:
            close([transport])


@pytest.mark.real_time
def test_killed_slave_process_is_lost_once_its_frames_stay_lost(link):
    """The slaves' process killed: its first LOST_FRAMES_IN_A_ROW frames are ridden through
    as lost ones (a bit error looks the same to a master), the next fails the line."""
    with slaves(link, 1) as line, link.entered():
        [transport] = open_ethercat_transports(link.master_port, [0], clock=clock_for(True),
                                               response_timeout=0.2)
        try:
            bring_up([transport])
            for _ in range(10):
                transport.exchange()
            line.kill()
            for _ in range(LOST_FRAMES_IN_A_ROW):
                with pytest.raises(SampleLost):
                    transport.exchange()
            with pytest.raises(DriveLost, match="no frame came back"):
                transport.exchange()
            # the first frames after the kill
            assert transport.line.frames == 11 + LOST_FRAMES_IN_A_ROW
            assert isinstance(transport.failure, DriveLost)
        finally:
            close([transport])


@pytest.mark.real_time
def test_bootstrap_request_is_refused_by_name(link):
    with slaves(link, 1), link.entered():
        master = pysoem.Master()
        master.open(link.master_port)
        try:
            master.config_init()
            slave = master.slaves[0]
            slave.state = pysoem.BOOT_STATE
            slave.write_state()
            assert slave.state_check(pysoem.BOOT_STATE, 200_000) & 0x0F == pysoem.PREOP_STATE
            master.read_state()
            assert slave.state == pysoem.PREOP_STATE | ec.AL_ERROR
            assert ec.al_status_name(slave.al_status) == "bootstrap not supported (0x0013)"
        finally:
            master.close()


@pytest.mark.real_time
def test_safe_op_refused_for_a_wrong_output_size_names_the_code(link):
    with slaves(link, 1), link.entered():
        [transport] = open_ethercat_transports(link.master_port, [0], clock=clock_for(True))
        try:
            bring_up([transport])
            line = transport.line
            line.request_state(pysoem.PREOP_STATE)
            # SM2 re-programmed for 6 bytes while the RxPDO assigned carries 4
            sm2 = ec.REG_SM0 + 2 * ec.SM_SIZE
            transport.slave._fpwr(sm2 + ec.SM_OFFSET_ACTIVATE, b"\x00")
            transport.slave._fpwr(sm2 + 2, struct.pack("<H", 6))
            transport.slave._fpwr(sm2 + ec.SM_OFFSET_ACTIVATE, b"\x01")
            with pytest.raises(DriveError, match=r"SAFE_OP refused: slave 0 in PRE_OP \+ ERROR"
                                                 r", AL status code invalid output "
                                                 r"configuration \(0x001D\)"):
                line.request_state(pysoem.SAFEOP_STATE)
        finally:
            close([transport])


@pytest.mark.real_time
def test_master_loss_trips_the_watchdog_and_the_drive_stops_on_its_brake(link):
    with slaves(link, 1) as line, link.entered():
        [drive] = open_ethercat_drives(link.master_port, [joint(0)], clock=clock_for(False))
        drive.start()
        for _ in range(50):
            with contextlib.suppress(SampleLost):  # a cycle skipped, as the loop skips it
                drive.sync()
            drive.command_current(0.2)
        # in OP on the wall clock SOEM polls for its frames (`_poll_for_frames`), but an
        # access outside the cycle (CoE, the keeper's frame) waits for its own asleep,
        # nested ones too, and the cycle polls again after it (`acyclic`)
        sockets = _packet_sockets(link.master_port)
        assert sockets and not any(os.get_blocking(fd) for fd in sockets)
        transport = drive.transport
        seen = transport._mailbox(lambda *_: [os.get_blocking(fd) for fd in sockets],
                                  objects.MAX_CURRENT, 0)
        assert seen == [True] * len(sockets)
        with transport.line.acyclic():
            with transport.line.acyclic():
                assert transport.read(objects.MAX_CURRENT) > 0  # answered, waited asleep
            assert all(os.get_blocking(fd) for fd in sockets)
        assert not any(os.get_blocking(fd) for fd in sockets)
        # the master dies: no close, no more frames (its socket goes with its process)
        drive.transport.line.master.close()
        time.sleep(0.5)
        [slave] = line.report()
    assert slave["al_status"] == ec.AlState.SAFE_OP | ec.AL_ERROR
    assert slave["al_status_code"] == ec.AL_SM_WATCHDOG
    assert "watchdog" in slave["master_loss"]
    assert slave["state"] in ("QUICK_STOP_ACTIVE", "SWITCH_ON_DISABLED")
    assert slave["brake_engaged"]


@pytest.mark.real_time
def test_drive_fault_arrives_as_a_coe_emergency_with_its_code(link):
    with slaves(link, 1), link.entered():
        [drive] = open_ethercat_drives(link.master_port, [joint(0)], clock=clock_for(True))
        try:
            drive.start()
            drive.sync()
            drive.transport.write(objects.FAULT_INJECTION, 0, 7)  # over-current trip
            sample = drive.sync()  # shows the fault; the emergency came with it
            assert sample.statusword & 0x0008
            assert isinstance(drive.fault, DriveFault) and drive.fault.error_code == 0x2310
            with pytest.raises(DriveFault, match=r"EMCY 0x2310"):
                drive.command_current(0.0)
        finally:
            drive.close()
    assert drive.last_emergency.register == 0x02


@pytest.mark.real_time
def test_malformed_frames_do_not_stop_the_line(link):
    with slaves(link, 2) as line, link.entered():
        raw = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ec.ETHERTYPE))
        raw.bind((link.master_port, ec.ETHERTYPE))
        raw.settimeout(2.0)
        good = ec.encode_frame([(ec.Command.BRD, 1, 0, bytes(2))])
        bad = [
            good[:12] + b"\x08\x00" + good[14:],  # IPv4
            good[:15],  # cut in the EtherCAT header
            good[:14] + struct.pack("<H", 0x1000 | 0x7FF) + good[16:],  # length past the end
            good[:14] + struct.pack("<H", 0x4000 | 12) + good[16:],  # frame type 4
            good[:16] + b"\x3f" + good[17:],  # unknown command
            good[:14] + b"\xff" * 46,
        ]
        try:
            for frame in bad:
                raw.send(frame)
            raw.send(good)
            answers = []
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline and len(answers) < 2:
                answers.append(raw.recv(1600))
        finally:
            raw.close()
        report = line.report()
    wkcs = [ec.datagram_result(a, ec.datagram_spans(a)[0])[1] for a in answers]
    assert wkcs == [0, 2]  # the unknown command untouched, then the good frame by both
    assert len(report) == 2


@pytest.mark.real_time
def test_a_stalled_controller_holds_the_command_instead_of_tripping_the_watchdog(link):
    """Real time: the line's own keeper sends frames while the cycle stalls (a cold solve, a
    collection), so the slaves' 100 ms watchdog never fires for a master that is alive."""
    with slaves(link, 2) as line, link.entered():
        drives = open_ethercat_drives(link.master_port, [joint(0), joint(1)],
                                      clock=clock_for(False))
        group = DriveGroup(["a", "b"], [EthercatLine(f"ethercat:{link.master_port}",
                                                     list(zip(["a", "b"], drives,
                                                              strict=True)))])
        try:
            group.start()
            for _ in range(20):
                with contextlib.suppress(SampleLost):  # a cycle skipped, as the loop skips it
                    group.sync()
                group.command_currents([0.1, -0.1])
                time.sleep(0.001)
            time.sleep(0.5)  # five watchdog times without a cycle
            for _ in range(20):
                with contextlib.suppress(SampleLost):
                    table = group.sync()
                group.command_currents([0.1, -0.1])
                time.sleep(0.001)
            assert [round(c, 1) for c in table[:, SAMPLE_MOTOR_CURRENT]] == [0.1, -0.1]
        finally:
            group.close()
        report = line.report()
    assert [r["master_loss"] for r in report] == [None, None]



class _Recording(pysoem.Master):
    """SOEM's master, noting how long SOEM waits for an acyclic frame at each step."""

    waits: dict[str, int] = {}

    def config_init(self, *args):
        self.waits["config_init"] = pysoem.settings.timeouts.ret
        return super().config_init(*args)

    def config_map(self, *args):
        self.waits["config_map"] = pysoem.settings.timeouts.ret
        return super().config_map(*args)


@pytest.mark.real_time
def test_the_master_configures_waiting_for_late_frames_and_cycles_with_soems_wait(link):
    """Real time: while the line is configured SOEM waits 20 ms for an acyclic frame, not its
    2 ms. A frame later than SOEM waits still carries its mailbox request to the slave, whose
    answer SOEM then takes for the next SDO read of the same object (it checks the index, not
    the subindex): config_map sums a wrong PDO length and the slave refuses SAFE-OP (0x001E,
    talos_32's virtual line on a loaded host: 2 starts in 8). From OP on, SOEM's own 2 ms: a
    cycle's state read must not wait longer."""
    with slaves(link, 2), link.entered():
        drives = open_ethercat_drives(link.master_port, [joint(0), joint(1)],
                                      clock=clock_for(False), open_master=_Recording)
        try:
            for drive in drives:
                drive.start()
            assert drives[0].transport.line.operational
            assert pysoem.settings.timeouts.ret == 2_000
        finally:
            for drive in drives:
                drive.close()
    assert _Recording.waits == {"config_init": 20_000, "config_map": 20_000}


class _Misread(pysoem.Master):
    """SOEM's master whose reads of the first slave's RxPDO find one entry, not two, as a
    lost or late mailbox answer makes them (the slave's own assignment changed to match, so
    only the master can tell)."""

    def config_map(self, *args):
        slave = self.slaves[0]
        slave.sdo_write(0x1C12, 0, b"\x00")
        slave.sdo_write(0x1600, 0, b"\x01")
        slave.sdo_write(0x1C12, 0, b"\x01")
        return super().config_map(*args)


@pytest.mark.real_time
def test_a_process_image_other_than_the_pdos_written_is_refused_by_name(link):
    """SOEM sizes the image from its own reads of the assignment: an image that is not what
    the transport mapped is one clear error naming the slave, not a cycle that cannot decode
    its frames (talos_32 beside two busy loops: "internal error: unpack requires a buffer of
    4 bytes")."""
    with slaves(link, 1), link.entered():
        drives = open_ethercat_drives(link.master_port, [joint(0)], clock=clock_for(False),
                                      open_master=_Misread)
        try:
            with pytest.raises(DriveError, match=r"slave 0: SOEM mapped 2 output and 16 input "
                                                 r"bytes where the PDOs written carry 4 and 16"):
                drives[0].start()
        finally:
            drives[0].close()
