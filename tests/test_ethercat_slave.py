"""The virtual slave's firmware with the real CiA 402 device, frames passed in-process: the
EtherCAT state machine and its refusals, SM-synchronous cycles, the process data watchdog,
emergencies in the mailbox, the communication faults, and random frames against a line in OP."""

import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from model.parameters import load_model
from protocol import ethercat as ec
from protocol import objects
from protocol.cia402 import State
from sim_bus.device import Cia402Device
from sim_bus.ethercat.segment import Segment
from sim_bus.faults import Fault

Cmd = ec.Command
AL = ec.AlState
MODEL = load_model()


class Master:
    """Just enough of a master to drive a line frame by frame."""

    def __init__(self, count: int = 1):
        self.segment = Segment([Cia402Device(MODEL) for _ in range(count)])
        self.now = 0.0
        self.counter = 0
        for k in range(count):
            self.send(Cmd.APWR, (-k & 0xFFFF) | ec.REG_STATION_ADDRESS << 16,
                      struct.pack("<H", 0x1001 + k))

    def send(self, command, address, data) -> tuple[bytes, int]:
        frame = bytearray(ec.encode_frame([(command, 0, address, data)]))
        assert self.segment.process(frame, len(frame), self.now)
        return ec.datagram_result(frame, ec.datagram_spans(frame)[0])

    def write(self, slave, register, data) -> int:
        return self.send(Cmd.FPWR, 0x1001 + slave | register << 16, data)[1]

    def read(self, slave, register, size) -> bytes:
        return self.send(Cmd.FPRD, 0x1001 + slave | register << 16, bytes(size))[0]

    def al(self, slave, control) -> tuple[int, int]:
        self.write(slave, ec.REG_AL_CONTROL, struct.pack("<H", control))
        status, _, code = struct.unpack("<HHH", self.read(slave, ec.REG_AL_STATUS, 6))
        return status, code

    def mailbox_config(self, slave, length=128):
        self.write(slave, ec.REG_SM0, ec.SYNC_MANAGER.pack(0x1000, length, 0x26, 0, 1, 0)
                   + ec.SYNC_MANAGER.pack(0x1080, 128, 0x22, 0, 1, 0))

    def process_data_config(self, slave, outputs=4, inputs=18):
        count = len(self.segment.escs)
        self.write(slave, ec.REG_SM0 + 16, ec.SYNC_MANAGER.pack(0x1100, outputs, 0x64, 0, 1, 0)
                   + ec.SYNC_MANAGER.pack(0x1180, inputs, 0x20, 0, 1, 0))
        self.write(slave, ec.REG_FMMU0, ec.FMMU.pack(4 * slave, 4, 0, 7, 0x1100, 0, 2, 1)
                   + ec.FMMU.pack(4 * count + 18 * slave, 18, 0, 7, 0x1180, 0, 1, 1))

    def sdo_download(self, slave, index, subindex, value: bytes) -> bytes:
        self.counter = self.counter % 7 + 1
        body = (ec.COE_HEADER.pack(ec.COE_SDO_REQUEST << 12)
                + ec.SDO_HEADER.pack(0x23 | (4 - len(value)) << 2, index, subindex)
                + value.ljust(4, b"\x00"))
        message = ec.MAILBOX_HEADER.pack(len(body), 0, 0, 3 | self.counter << 4) + body
        assert self.write(slave, 0x1000, message.ljust(128, b"\x00")) == 1
        return self.mailbox(slave)

    def mailbox(self, slave) -> bytes | None:
        data, wkc = self.send(Cmd.FPRD, 0x1001 + slave | 0x1080 << 16, bytes(128))
        return data if wkc else None

    def operational(self, slave=0):
        self.mailbox_config(slave)
        assert self.al(slave, AL.PRE_OP) == (AL.PRE_OP, 0)
        self.process_data_config(slave)
        assert self.al(slave, AL.SAFE_OP) == (AL.SAFE_OP, 0)
        assert self.al(slave, AL.OP) == (AL.SAFE_OP, 0)  # OP comes with the first outputs
        self.cycle()
        assert self.al(slave, AL.OP)[0] == AL.OP

    def cycle(self, outputs: bytes | None = None) -> tuple[bytes, int]:
        count = len(self.segment.escs)
        data = (outputs or bytes(4 * count)) + bytes(18 * count)
        self.now += 1e-3
        return self.send(Cmd.LRW, 0, data)


def test_init_to_pre_op_checks_the_mailbox_against_the_sii():
    master = Master()
    master.mailbox_config(0, length=16)
    assert master.al(0, AL.PRE_OP) == (AL.INIT | ec.AL_ERROR,
                                       ec.AL_INVALID_MAILBOX_CONFIGURATION)
    assert master.al(0, AL.PRE_OP) == (AL.INIT | ec.AL_ERROR,
                                       ec.AL_INVALID_MAILBOX_CONFIGURATION)  # no ack: blocked
    master.write(0, ec.REG_SM0 + ec.SM_OFFSET_ACTIVATE, b"\x00")
    master.mailbox_config(0)
    assert master.al(0, AL.PRE_OP | ec.AL_ERROR) == (AL.PRE_OP, 0)  # acknowledged


@pytest.mark.parametrize("request_,code", [
    (AL.SAFE_OP, ec.AL_INVALID_STATE_CHANGE), (AL.OP, ec.AL_INVALID_STATE_CHANGE),
    (AL.BOOT, ec.AL_BOOTSTRAP_NOT_SUPPORTED), (0x05, ec.AL_UNKNOWN_STATE)])
def test_requests_the_state_machine_refuses(request_, code):
    master = Master()
    assert master.al(0, request_) == (AL.INIT | ec.AL_ERROR, code)
    assert master.al(0, AL.INIT | ec.AL_ERROR) == (AL.INIT, 0)


def test_safe_op_needs_sync_managers_that_fit_the_assigned_pdos():
    master = Master()
    master.mailbox_config(0)
    master.al(0, AL.PRE_OP)
    master.process_data_config(0, inputs=16)
    assert master.al(0, AL.SAFE_OP) == (AL.PRE_OP | ec.AL_ERROR,
                                        ec.AL_INVALID_INPUT_CONFIGURATION)
    master.write(0, ec.REG_SM0 + 3 * 8 + ec.SM_OFFSET_ACTIVATE, b"\x00")
    master.process_data_config(0)
    assert master.al(0, AL.SAFE_OP | ec.AL_ERROR) == (AL.SAFE_OP, 0)


def test_each_output_frame_is_one_device_cycle_and_carries_its_result():
    master = Master(2)
    for slave in (0, 1):
        master.operational(slave)
    devices = [f.device for f in master.segment.firmwares]
    for device in devices:
        device.write(objects.MODES_OF_OPERATION, 0, objects.MODE_CYCLIC_SYNC_TORQUE)
        for controlword in (6, 7, 15):
            device.write(objects.CONTROLWORD, 0, controlword)
    before = [d.cycle_count for d in devices]
    data, wkc = master.cycle(struct.pack("<Hh", 15, 300) + struct.pack("<Hh", 15, -300))
    assert wkc == 6
    assert [d.cycle_count for d in devices] == [b + 1 for b in before]
    for slave, device in enumerate(devices):
        statusword, position = struct.unpack_from("<Hi", data, 8 + 18 * slave)
        assert position == device.read(objects.POSITION_ACTUAL)  # this cycle's sample
        assert device.applied_current == pytest.approx(
            (1 if slave == 0 else -1) * 0.3 * device.rated_torque / device.drive_gain)


def test_outputs_are_not_applied_before_op():
    master = Master()
    master.mailbox_config(0)
    master.al(0, AL.PRE_OP)
    master.process_data_config(0)
    master.al(0, AL.SAFE_OP)
    device = master.segment.firmwares[0].device
    master.cycle(struct.pack("<Hh", 6, 0))
    assert device.state is State.SWITCH_ON_DISABLED
    assert device.cycle_count == 1  # time runs in SAFE-OP, the outputs wait for OP


def test_watchdog_takes_the_slave_out_of_op_and_stops_the_drive():
    master = Master()
    master.operational()
    device = master.segment.firmwares[0].device
    for controlword in (6, 7, 15):
        device.write(objects.CONTROLWORD, 0, controlword)
    master.cycle(struct.pack("<Hh", 15, 0))
    master.segment.check_watchdogs(master.now + 0.05)
    assert device.state is State.OPERATION_ENABLED
    master.segment.check_watchdogs(master.now + 0.2)
    status, _, code = struct.unpack("<HHH", master.read(0, ec.REG_AL_STATUS, 6))
    assert (status, code) == (AL.SAFE_OP | ec.AL_ERROR, ec.AL_SM_WATCHDOG)
    assert device.state in (State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED)
    assert device.brake_engaged and "watchdog" in device.master_loss
    _, wkc = master.cycle()
    assert wkc == 3  # SAFE-OP still exchanges data, the outputs are not applied


def test_emergency_waits_in_the_mailbox():
    master = Master()
    master.operational()
    reply = master.sdo_download(0, objects.FAULT_INJECTION, 0, bytes([Fault.OVERCURRENT_TRIP]))
    assert reply[8] == ec.SDO_SCS_DOWNLOAD  # the download's answer first
    emergency = master.mailbox(0)
    assert struct.unpack_from("<HHB", emergency, 6) == (ec.COE_EMERGENCY << 12,
                                                        0x2310, 0x02)
    assert master.mailbox(0) is None


def test_an_answer_goes_before_an_emergency_still_queued():
    """A drive fault raised between two frames queues its emergency; the master's next
    request is answered first, the emergency after (a master waiting for its answer need
    not handle another message first: SOEM 2.0 crashes on one)."""
    master = Master()
    master.operational()
    master.segment.firmwares[0].device.inject(Fault.OVERCURRENT_TRIP)  # the drive's own thread
    reply = master.sdo_download(0, objects.MODES_OF_OPERATION, 0, bytes([10]))
    assert struct.unpack_from("<H", reply, 6)[0] >> 12 == ec.COE_SDO_RESPONSE
    assert reply[8] == ec.SDO_SCS_DOWNLOAD
    emergency = master.mailbox(0)
    assert struct.unpack_from("<HH", emergency, 6) == (ec.COE_EMERGENCY << 12, 0x2310)
    assert master.mailbox(0) is None


def test_silent_and_reboot_faults():
    master = Master(2)
    for slave in (0, 1):
        master.operational(slave)
    master.segment.firmwares[0].device.inject(Fault.SILENT)
    _, wkc = master.cycle()
    assert wkc == 3  # slave 1 alone
    master.segment.firmwares[1].device.inject(Fault.REBOOT)
    assert master.segment.escs[1].station_address == 0
    _, wkc = master.send(Cmd.BRD, ec.REG_AL_STATUS << 16, bytes(2))
    assert wkc == 1 and master.segment.escs[1].al_status == AL.INIT


line_datagram = st.tuples(st.sampled_from(list(Cmd) + [0x2A, 0xFF]), st.integers(0, 0xFFFF),
                          st.sampled_from([0, 0x10, 0x120, 0x130, 0x502, 0x600, 0x800, 0x80D,
                                           0x1000, 0x1080, 0x1100, 0x1180, 0xFFF0]),
                          st.binary(max_size=140))


@pytest.fixture(scope="module")
def line_in_op():
    master = Master(2)
    master.operational(0)
    return master


@settings(max_examples=300, deadline=None, suppress_health_check=[
    HealthCheck.function_scoped_fixture])
@given(datagrams=st.lists(line_datagram, min_size=1, max_size=5))
def test_random_datagrams_against_a_line_in_op_never_crash(line_in_op, datagrams):
    """One line takes every example, so the random writes pile up as on a real wire."""
    frame = bytearray(ec.encode_frame([(c, 0, adp | ado << 16, d) for c, adp, ado, d
                                       in datagrams]))
    line_in_op.segment.process(frame, len(frame), 1.0)
    line_in_op.segment.check_watchdogs(1.0)
