"""The emulated EtherCAT slave controller, frame by frame: addressing modes and working
counters, read-only registers, the SII EEPROM interface, mailbox sync managers, FMMU process
data in lock-step, and frames an ESC does not process."""

import struct

from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import esi_path
from protocol import ethercat as ec
from protocol.esi import load_esi
from protocol.sii import build_sii
from sim_bus.ethercat.esc import Esc
from sim_bus.ethercat.segment import pass_frame

Cmd = ec.Command


class RecordingFirmware:
    """Stands behind the PDI: acknowledges states as asked, echoes the outputs into the
    inputs (so a frame shows whether the cycle ran before its inputs were read)."""

    def __init__(self):
        self.controls: list[int] = []
        self.mailboxes: list[bytes] = []
        self.cycles = 0
        self.expired = 0

    def al_control(self, esc, control):
        self.controls.append(control)
        esc.set_al_status(control & ec.AL_STATE_MASK, 0)

    def mailbox_received(self, esc, message):
        self.mailboxes.append(message)

    def mailbox_read(self, esc):
        pass

    def mailbox_repeat(self, esc):
        pass

    def outputs_received(self, esc):
        self.cycles += 1
        out = bytes(esc.memory[0x1100:0x1104])
        esc.memory[0x1180:0x1184] = out[::-1]
        esc.memory[0x1184] = self.cycles

    def watchdog_expired(self, esc):
        self.expired += 1

    def frame_passed(self, esc):
        pass

    def mail_waiting(self):
        return False


ESI = load_esi(esi_path())
SII = build_sii(ESI)


def line(n: int = 3) -> list[Esc]:
    escs = [Esc(SII, RecordingFirmware()) for _ in range(n)]
    for k, esc in enumerate(escs):
        esc.set_link(last=k == n - 1)
    return escs


def exchange(escs, *datagrams, now=0.0):
    """Send (command, address, data) datagrams through the line; (data, wkc) of each."""
    frame = bytearray(ec.encode_frame([(c, k, a, d) for k, (c, a, d) in enumerate(datagrams)]))
    assert pass_frame(escs, frame, len(frame), now)
    return [ec.datagram_result(frame, s) for s in ec.datagram_spans(frame)]


def physical(adp: int, ado: int) -> int:
    return adp | ado << 16


def u16(value: int) -> bytes:
    return struct.pack("<H", value)


def configure(escs):
    """Station addresses 0x1001.. by auto-increment, as SOEM's config_init does."""
    for k in range(len(escs)):
        [(_, wkc)] = exchange(escs, (Cmd.APWR, physical(-k & 0xFFFF, ec.REG_STATION_ADDRESS),
                                     u16(0x1001 + k)))
        assert wkc == 1


def test_broadcast_read_counts_slaves_and_ors_their_data():
    escs = line(3)
    [(data, wkc)] = exchange(escs, (Cmd.BRD, physical(0, ec.REG_TYPE), bytes(2)))
    assert wkc == 3
    assert data[0] == 0x11  # ET1100


def test_auto_increment_and_configured_addressing():
    escs = line(3)
    configure(escs)
    assert [esc.station_address for esc in escs] == [0x1001, 0x1002, 0x1003]
    [(data, wkc)] = exchange(escs, (Cmd.FPRD, physical(0x1002, ec.REG_STATION_ADDRESS),
                                    bytes(2)))
    assert (data, wkc) == (u16(0x1002), 1)
    [(_, wkc)] = exchange(escs, (Cmd.FPRD, physical(0x2000, ec.REG_STATION_ADDRESS), bytes(2)))
    assert wkc == 0  # nobody has that address
    frame = bytearray(ec.encode_frame([(Cmd.APRD, 0, physical(0xFFFE, 0), bytes(2))]))
    pass_frame(escs, frame, len(frame), 0.0)
    adp = struct.unpack_from("<H", frame, ec.datagram_spans(frame)[0][1] + 2)[0]
    assert adp == 1  # every slave incremented it on the way: 0xFFFE + 3


def test_read_write_commands_count_one_for_the_read_and_two_for_the_write():
    escs = line(2)
    configure(escs)
    [(data, wkc)] = exchange(escs, (Cmd.FPRW, physical(0x1001, ec.REG_ECAT_EVENT_MASK),
                                    u16(0x1234)))
    assert (data, wkc) == (u16(0), 3)  # old value read, new value written
    [(data, _)] = exchange(escs, (Cmd.FPRD, physical(0x1001, ec.REG_ECAT_EVENT_MASK),
                                  bytes(2)))
    assert data == u16(0x1234)
    [(_, wkc)] = exchange(escs, (Cmd.BWR, physical(0, ec.REG_ECAT_EVENT_MASK), u16(7)))
    assert wkc == 2


def test_read_multiple_write_spreads_the_addressed_slaves_value():
    escs = line(3)
    configure(escs)
    exchange(escs, (Cmd.FPWR, physical(0x1001, ec.REG_ECAT_EVENT_MASK), u16(0xBEEF)))
    [(data, wkc)] = exchange(escs, (Cmd.FRMW, physical(0x1001, ec.REG_ECAT_EVENT_MASK),
                                    bytes(2)))
    assert (data, wkc) == (u16(0xBEEF), 3)
    [(data, _)] = exchange(escs, (Cmd.FPRD, physical(0x1003, ec.REG_ECAT_EVENT_MASK),
                                  bytes(2)))
    assert data == u16(0xBEEF)


def test_read_only_registers_ignore_writes():
    escs = line(1)
    [(_, wkc)] = exchange(escs, (Cmd.BWR, physical(0, ec.REG_AL_STATUS), u16(0x08)),
                          (Cmd.BWR, physical(0, ec.REG_TYPE), b"\x00"))[:1]
    assert wkc == 1
    assert escs[0].al_status == ec.AlState.INIT
    assert escs[0].memory[ec.REG_TYPE] == 0x11


def test_al_control_reaches_the_firmware():
    escs = line(2)
    exchange(escs, (Cmd.BWR, physical(0, ec.REG_AL_CONTROL),
                    u16(ec.AlState.PRE_OP | ec.AL_ERROR)))
    assert [esc.firmware.controls for esc in escs] == [[0x12], [0x12]]
    [(data, wkc)] = exchange(escs, (Cmd.BRD, physical(0, ec.REG_AL_STATUS), bytes(2)))
    assert (data, wkc) == (u16(ec.AlState.PRE_OP), 2)


def test_sii_read_through_the_eeprom_registers():
    escs = line(2)
    configure(escs)
    [(status, _)] = exchange(escs, (Cmd.FPRD, physical(0x1002, ec.REG_EEPROM_CONTROL),
                                    bytes(2)))
    assert struct.unpack("<H", status)[0] & ec.EEPROM_READ_8_BYTES
    for word in (ec.SII_WORD_VENDOR_ID, ec.SII_WORD_PRODUCT_CODE, 0x40, 0x3FE):
        command = struct.pack("<HHH", ec.EEPROM_COMMAND_READ, word, 0)
        exchange(escs, (Cmd.FPWR, physical(0x1002, ec.REG_EEPROM_CONTROL), command))
        [(data, wkc)] = exchange(escs, (Cmd.FPRD, physical(0x1002, ec.REG_EEPROM_DATA),
                                        bytes(8)))
        assert wkc == 1
        expected = SII[word * 2:word * 2 + 8]
        assert data == expected + b"\xff" * (8 - len(expected))
    assert struct.unpack_from("<III", SII, 16) == ESI.identity


def test_eeprom_write_needs_the_write_enable_bit():
    escs = line(1)
    configure(escs)
    exchange(escs, (Cmd.FPWR, physical(0x1001, ec.REG_EEPROM_DATA), u16(0xABCD)))
    exchange(escs, (Cmd.FPWR, physical(0x1001, ec.REG_EEPROM_CONTROL),
                    struct.pack("<HHH", ec.EEPROM_COMMAND_WRITE, 0x30, 0)))
    [(status, _)] = exchange(escs, (Cmd.FPRD, physical(0x1001, ec.REG_EEPROM_CONTROL),
                                    bytes(2)))
    assert struct.unpack("<H", status)[0] & ec.EEPROM_ERROR_WRITE_ENABLE
    exchange(escs, (Cmd.FPWR, physical(0x1001, ec.REG_EEPROM_CONTROL), struct.pack(
        "<HHH", ec.EEPROM_COMMAND_WRITE | ec.EEPROM_WRITE_ENABLE, 0x30, 0)))
    assert escs[0].eeprom[0x60:0x62] == u16(0xABCD)


def sync_manager(start: int, length: int, control: int, enable: bool = True) -> bytes:
    return ec.SYNC_MANAGER.pack(start, length, control, 0, int(enable), 0)


def test_mailbox_sync_managers_hand_over_whole_buffers():
    escs = line(1)
    configure(escs)
    [(_, wkc)] = exchange(escs, (Cmd.FPWR, physical(0x1001, ec.REG_SM0),
                                 sync_manager(0x1000, 128, 0x26)
                                 + sync_manager(0x1080, 128, 0x22)))
    assert wkc == 1
    message = bytes(range(128))
    [(_, wkc)] = exchange(escs, (Cmd.FPWR, physical(0x1001, 0x1000), message[:64]))
    assert wkc == 1 and escs[0].firmware.mailboxes == []  # not complete yet
    exchange(escs, (Cmd.FPWR, physical(0x1001, 0x1040), message[64:]))
    assert escs[0].firmware.mailboxes == [message]
    # the slave answers in SM1: full until the master read its last byte
    assert escs[0].post_mailbox(1, b"reply")
    assert not escs[0].post_mailbox(1, b"second")  # still full
    [(status, _)] = exchange(escs, (Cmd.FPRD, physical(0x1001, 0x080D), bytes(1)))
    assert status[0] & ec.SM_STATUS_MAILBOX_FULL
    [(data, wkc)] = exchange(escs, (Cmd.FPRD, physical(0x1001, 0x1080), bytes(128)))
    assert (data[:5], wkc) == (b"reply", 1)
    [(_, wkc)] = exchange(escs, (Cmd.FPRD, physical(0x1001, 0x1080), bytes(128)))
    assert wkc == 0  # empty: the read is refused
    [(_, wkc)] = exchange(escs, (Cmd.FPWR, physical(0x1001, 0x1080), bytes(128)))
    assert wkc == 0  # the master cannot write the slave's mailbox


def map_process_data(escs):
    """SM2 4 bytes at 0x1100, SM3 5 bytes at 0x1180; slave k's outputs at logical 4k, its
    inputs after all outputs, as SOEM's config_map lays them out."""
    n = len(escs)
    for k in range(n):
        address = 0x1001 + k
        exchange(escs, (Cmd.FPWR, physical(address, ec.REG_SM0 + 16),
                        sync_manager(0x1100, 4, 0x64) + sync_manager(0x1180, 5, 0x20)))
        exchange(escs, (Cmd.FPWR, physical(address, ec.REG_FMMU0),
                        ec.FMMU.pack(4 * k, 4, 0, 7, 0x1100, 0, ec.FMMU_WRITE, 1)
                        + ec.FMMU.pack(4 * n + 5 * k, 5, 0, 7, 0x1180, 0, ec.FMMU_READ, 1)))


def test_logical_read_write_runs_the_cycle_before_the_inputs_are_read():
    escs = line(3)
    configure(escs)
    map_process_data(escs)
    outputs = b"".join(bytes([k, 1, 2, 3]) for k in range(3))
    [(data, wkc)] = exchange(escs, (Cmd.LRW, 0, outputs + bytes(15)))
    assert wkc == 3 * 3
    for k in range(3):
        assert data[4 * k:4 * k + 4] == outputs[4 * k:4 * k + 4]  # outputs stay
        assert data[12 + 5 * k:17 + 5 * k] == bytes([3, 2, 1, k, 1])  # this frame's cycle
    assert [esc.firmware.cycles for esc in escs] == [1, 1, 1]
    [(_, wkc)] = exchange(escs, (Cmd.LRD, 12, bytes(15)))
    assert wkc == 3 and [esc.firmware.cycles for esc in escs] == [1, 1, 1]
    [(_, wkc)] = exchange(escs, (Cmd.LWR, 0, outputs))
    assert wkc == 3 and [esc.firmware.cycles for esc in escs] == [2, 2, 2]


def test_deactivated_process_data_sync_managers_refuse_the_master():
    escs = line(1)
    configure(escs)
    map_process_data(escs)
    escs[0].set_sync_manager_active(2, False)
    [(_, wkc)] = exchange(escs, (Cmd.LRW, 0, bytes(9)))
    assert wkc == 1  # only the inputs
    assert escs[0].firmware.cycles == 0


def test_process_data_watchdog_counts_wall_time_from_the_last_output_buffer():
    escs = line(1)
    configure(escs)
    map_process_data(escs)
    exchange(escs, (Cmd.LWR, 0, bytes(4)), now=10.0)
    escs[0].check_watchdog(10.05)
    assert escs[0].firmware.expired == 0
    escs[0].check_watchdog(10.2)  # default 100 ms
    assert escs[0].firmware.expired == 1
    assert escs[0].memory[ec.REG_WATCHDOG_STATUS_PROCESS_DATA] & 0x01 == 0
    assert escs[0].memory[ec.REG_WATCHDOG_COUNTER_PROCESS_DATA] == 1


def test_nop_and_unknown_commands_pass_untouched():
    escs = line(2)
    [(data, wkc), (data2, wkc2)] = exchange(escs, (Cmd.NOP, 0, b"abcd"), (0x3F, 0, b"efgh"))
    assert (data, wkc, data2, wkc2) == (b"abcd", 0, b"efgh", 0)


def test_frames_an_esc_does_not_process_are_dropped_and_counted():
    escs = line(1)
    good = bytearray(ec.encode_frame([(Cmd.BRD, 0, 0, bytes(2))]))
    other_ethertype = bytearray(good)
    other_ethertype[12:14] = b"\x08\x00"
    cut = good[:20]
    wrong_type = bytearray(good)
    wrong_type[15] = 0x40  # EtherCAT frame type 4
    for frame in (other_ethertype, cut, wrong_type):
        assert not pass_frame(escs, frame, len(frame), 0.0)
    assert escs[0].memory[ec.REG_RX_ERROR_COUNTER] == 3


@settings(max_examples=300, deadline=None)
@given(st.binary(min_size=0, max_size=200))
def test_random_bytes_never_crash_the_line(payload):
    escs = line(2)
    frame = bytearray(ec.encode_frame([])[:14] + payload)
    pass_frame(escs, frame, len(frame), 0.0)


datagram = st.tuples(st.integers(0, 255), st.integers(0, 0xFFFFFFFF),
                     st.binary(min_size=0, max_size=64))


@settings(max_examples=300, deadline=None)
@given(st.lists(datagram, min_size=1, max_size=6), st.integers(0, 0x7FF))
def test_well_formed_frames_with_any_command_and_address_never_crash(datagrams, cut):
    escs = line(2)
    configure(escs)
    map_process_data(escs)
    frame = bytearray(ec.encode_frame([(c, 0, a, d) for c, a, d in datagrams]))
    pass_frame(escs, frame, len(frame), 0.0)
    pass_frame(escs, frame, min(len(frame), cut), 0.0)
