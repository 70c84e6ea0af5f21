"""An EtherCAT slave controller (ESC) as the master sees it: the ET1100 register file, the
datagram commands with their addressing and working counters, sync managers (mailbox and
buffered), FMMUs mapping the logical process image, the SII EEPROM interface and the process
data watchdog.

Everything behind the PDI (the AL state machine, the mailbox protocols, the process data
application) is the slave's firmware, reached through the `Firmware` calls below; the ESC
calls them synchronously, so the firmware reacts before the frame moves on to the next slave
(an infinitely fast slave controller: what makes each process data frame one lock-step cycle).

Hot path: logical datagrams go through precomputed FMMU tuples and memoryview copies into one
64 KiB bytearray; only register writes (bring-up traffic) take the byte-wise masked path.
"""

import struct
from typing import Protocol

from protocol import ethercat as ec
from sim_bus.ethercat import dc
from sim_bus.ethercat.dc import DistributedClock

ESC_TYPE_ET1100 = 0x11  # the register layout and behaviour followed here
RAM_END = 0x3000  # ET1100: 8 KiB process RAM from 0x1000
FMMU_COUNT = 8
SM_COUNT = 8
PORT_DESCRIPTOR_MII_01 = 0x0F  # ports 0 and 1 MII, ports 2 and 3 not implemented
PDI_CONTROL_SPI = 0x05  # overwritten from SII word 0 at power-on
AL_CONTROL_CHANGED = 0x0001  # AL event request bit for an AL control write
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")


class Firmware(Protocol):
    """The slave's application behind the PDI, as the ESC interrupts it."""

    def al_control(self, esc: "Esc", control: int) -> None:
        """The master wrote AL control (0x0120)."""

    def mailbox_received(self, esc: "Esc", message: bytes) -> None:
        """The master filled the mailbox-out sync manager (all of it was written)."""

    def mailbox_read(self, esc: "Esc") -> None:
        """The master emptied the mailbox-in sync manager: room for the next message."""

    def mailbox_repeat(self, esc: "Esc") -> None:
        """The master toggled the mailbox-in repeat request: send the last message again."""

    def outputs_received(self, esc: "Esc") -> None:
        """The master completed the output buffer (its last byte was written)."""

    def watchdog_expired(self, esc: "Esc") -> None:
        """No output buffer completed within the process data watchdog time."""

    def frame_passed(self, esc: "Esc") -> None:
        """A frame went through (the firmware's chance to post a queued mailbox message)."""

    def mail_waiting(self) -> bool:
        """Whether a message waits to be posted at the next frame: a frame no datagram of
        which reaches this slave (a configured-address read of another) passes it by
        otherwise."""

    def sync0(self, esc: "Esc") -> None:
        """The distributed clock's SYNC0 fired (cyclic operation with SYNC0 active)."""


def _writable_masks() -> bytes:
    """Which bits of each register the master may write (ET1100 'ECAT write access')."""
    masks = bytearray(ec.PROCESS_RAM_START)

    def allow(start: int, length: int, mask: int = 0xFF) -> None:
        masks[start:start + length] = bytes([mask]) * length

    allow(ec.REG_STATION_ADDRESS, 2)
    allow(ec.REG_DL_CONTROL, 4)
    allow(0x0108, 2)  # physical read/write offset
    allow(ec.REG_AL_CONTROL, 2)
    allow(ec.REG_ECAT_EVENT_MASK, 2)
    allow(ec.REG_RX_ERROR_COUNTER, 0x14)  # writing clears (below)
    allow(ec.REG_WATCHDOG_DIVIDER, 2)
    allow(ec.REG_WATCHDOG_TIME_PDI, 2)
    allow(ec.REG_WATCHDOG_TIME_PROCESS_DATA, 2)
    allow(ec.REG_WATCHDOG_COUNTER_PROCESS_DATA, 2)  # writing clears
    allow(ec.REG_EEPROM_CONFIGURATION, 1, 0x03)
    allow(ec.REG_EEPROM_CONTROL, 1, ec.EEPROM_WRITE_ENABLE)
    allow(ec.REG_EEPROM_CONTROL + 1, 1, ec.EEPROM_COMMAND_MASK >> 8)
    allow(ec.REG_EEPROM_ADDRESS, 4)
    allow(ec.REG_EEPROM_DATA, 8)
    allow(0x0510, 8)  # MII management
    allow(ec.REG_FMMU0, ec.FMMU_SIZE * FMMU_COUNT)
    for n in range(SM_COUNT):
        base = ec.REG_SM0 + n * ec.SM_SIZE
        allow(base, 5)  # start, length, control (only while disabled, see _write_registers)
        allow(base + ec.SM_OFFSET_ACTIVATE, 1)
    # distributed clocks (sim_bus.ethercat.dc): the latch trigger, compare value, offset,
    # delay, speed counter start and filter depths, cyclic unit, activation, start time and
    # the SYNC0/SYNC1 cycle times
    allow(dc.REG_RECEIVE_TIME_PORT0, 4)
    allow(dc.REG_SYSTEM_TIME, 8)
    allow(dc.REG_SYSTEM_TIME_OFFSET, 8)
    allow(dc.REG_SYSTEM_TIME_DELAY, 4)
    allow(dc.REG_SPEED_COUNTER_START, 2)
    allow(0x0934, 2)  # system time difference / speed counter filter depths
    allow(dc.REG_CYCLIC_UNIT_CONTROL, 2)
    allow(dc.REG_START_TIME, 8)
    allow(dc.REG_SYNC0_CYCLE_TIME, 8)
    allow(0x0F00, 4)  # digital outputs
    return bytes(masks)


_WRITABLE = _writable_masks()
_CLEAR_ON_WRITE = ((ec.REG_RX_ERROR_COUNTER, ec.REG_RX_ERROR_COUNTER + 0x14),
                   (ec.REG_WATCHDOG_COUNTER_PROCESS_DATA,
                    ec.REG_WATCHDOG_COUNTER_PROCESS_DATA + 2))


class Esc:
    """One slave controller: its memory, its EEPROM and its firmware."""

    def __init__(self, eeprom: bytes, firmware: Firmware):
        self.memory = bytearray(ec.ADDRESS_SPACE)
        self.view = memoryview(self.memory)
        self.eeprom = bytearray(eeprom)
        self.firmware = firmware
        self.present = True  # False: powered off, frames pass untouched
        self.now = 0.0  # s, set by the segment before each frame (watchdog time base)
        # active FMMUs: (logical start, logical end, physical start, reads, writes)
        self._fmmus: list[tuple[int, int, int, bool, bool]] = []
        # enabled sync managers in process RAM: (number, start, end, mailbox, master_writes,
        # watchdog trigger)
        self._sms: list[tuple[int, int, int, bool, bool, bool]] = []
        # the FMMUs as precomputed copies (writes, reads), or None: use the checked path
        self._plan: tuple[list, list] | None = ([], [])
        self._watchdog_period = 0.0
        self._watchdog_deadline: float | None = None
        self._last_in_line = True
        self.dc = DistributedClock(self.memory)
        self.power_on()

    # --- power-on ----------------------------------------------------------------------------

    def power_on(self) -> None:
        """Reset values and the ESC configuration area loaded from the EEPROM."""
        m = self.memory
        m[:] = bytes(ec.ADDRESS_SPACE)
        m[ec.REG_TYPE] = ESC_TYPE_ET1100
        m[ec.REG_FMMUS_SUPPORTED] = FMMU_COUNT
        m[ec.REG_SMS_SUPPORTED] = SM_COUNT
        m[ec.REG_RAM_SIZE] = (RAM_END - ec.PROCESS_RAM_START) // 1024
        m[ec.REG_PORT_DESCRIPTOR] = PORT_DESCRIPTOR_MII_01
        # distributed clocks with a 64-bit system time; all read/write commands supported
        _U16.pack_into(m, ec.REG_FEATURES, dc.FEATURE_DC | dc.FEATURE_DC_64BIT)
        _U16.pack_into(m, ec.REG_AL_STATUS, ec.AlState.INIT)
        _U16.pack_into(m, ec.REG_WATCHDOG_DIVIDER, ec.WATCHDOG_DIVIDER_DEFAULT)
        _U16.pack_into(m, ec.REG_WATCHDOG_TIME_PDI, ec.WATCHDOG_TIME_DEFAULT)
        _U16.pack_into(m, ec.REG_WATCHDOG_TIME_PROCESS_DATA, ec.WATCHDOG_TIME_DEFAULT)
        _U16.pack_into(m, ec.REG_EEPROM_CONTROL, ec.EEPROM_READ_8_BYTES)
        self.set_link(self._last_in_line)
        self._reload_configuration()
        self._fmmus, self._sms = [], []
        self._plan = ([], [])
        self._watchdog_deadline = None
        self._update_watchdog_period()
        self.dc.reset()

    def _reload_configuration(self) -> None:
        """ESC configuration area of the EEPROM into the registers (power-on, reload command);
        a bad checksum leaves the PDI non-operational, as on the chip."""
        area = bytes(self.eeprom[:ec.SII_CONFIG_BYTES + 2])
        valid = len(area) == ec.SII_CONFIG_BYTES + 2 and ec.crc8_sii(
            area[:ec.SII_CONFIG_BYTES]) == area[ec.SII_CONFIG_BYTES]
        status = _U16.unpack_from(self.memory, ec.REG_DL_STATUS)[0]
        if valid:
            self.memory[ec.REG_PDI_CONTROL:ec.REG_PDI_CONTROL + 2] = area[0:2]
            self.memory[ec.REG_STATION_ALIAS:ec.REG_STATION_ALIAS + 2] = area[
                ec.SII_WORD_STATION_ALIAS * 2:ec.SII_WORD_STATION_ALIAS * 2 + 2]
            status |= ec.DL_STATUS_PDI_OPERATIONAL
        else:
            status &= ~ec.DL_STATUS_PDI_OPERATIONAL
        _U16.pack_into(self.memory, ec.REG_DL_STATUS, status)

    def set_link(self, last: bool) -> None:
        """DL status of the ports: port 0 towards the master, port 1 open to the next slave
        unless this one ends the line (its loop closed)."""
        self._last_in_line = last
        status = (ec.DL_STATUS_PDI_WATCHDOG_OK | ec.DL_STATUS_LINK_PORT0
                  | ec.DL_STATUS_PORT0_OPEN | ec.DL_STATUS_PORT2_CLOSED
                  | ec.DL_STATUS_PORT3_CLOSED)
        status |= ec.DL_STATUS_PORT1_CLOSED if last else (
            ec.DL_STATUS_PORT1_OPEN | ec.DL_STATUS_LINK_PORT1)
        old = _U16.unpack_from(self.memory, ec.REG_DL_STATUS)[0]
        _U16.pack_into(self.memory, ec.REG_DL_STATUS,
                       status | (old & ec.DL_STATUS_PDI_OPERATIONAL))

    # --- what the firmware uses --------------------------------------------------------------

    @property
    def station_address(self) -> int:
        return _U16.unpack_from(self.memory, ec.REG_STATION_ADDRESS)[0]

    @property
    def al_status(self) -> int:
        return _U16.unpack_from(self.memory, ec.REG_AL_STATUS)[0]

    def set_al_status(self, status: int, code: int) -> None:
        _U16.pack_into(self.memory, ec.REG_AL_STATUS, status)
        _U16.pack_into(self.memory, ec.REG_AL_STATUS_CODE, code)

    def sync_manager(self, number: int) -> tuple[int, int, int, int]:
        """(start, length, control, activate) as the master configured it."""
        start, length, control, _, activate, _ = ec.SYNC_MANAGER.unpack_from(
            self.memory, ec.REG_SM0 + number * ec.SM_SIZE)
        return start, length, control, activate

    def set_sync_manager_active(self, number: int, active: bool) -> None:
        """PDI side of a sync manager: deactivated ones refuse master access (the firmware
        keeps the process data ones off until SAFE-OP)."""
        address = ec.REG_SM0 + number * ec.SM_SIZE + ec.SM_OFFSET_PDI_CONTROL
        if active:
            self.memory[address] &= ~ec.SM_PDI_DEACTIVATE
        else:
            self.memory[address] |= ec.SM_PDI_DEACTIVATE
        self._rebuild_sync_managers()

    def mailbox_in_empty(self, number: int) -> bool:
        status = ec.REG_SM0 + number * ec.SM_SIZE + ec.SM_OFFSET_STATUS
        return not self.memory[status] & ec.SM_STATUS_MAILBOX_FULL

    def post_mailbox(self, number: int, message: bytes) -> bool:
        """PDI writes a message into the mailbox-in buffer (padded to its length); False when
        the buffer is still full, too short, or placed by the master past the end of the
        ESC's memory (writing there would resize the memory under the frame's views)."""
        start, length, _, activate = self.sync_manager(number)
        if not activate & ec.SM_ACTIVATE_ENABLE or not self.mailbox_in_empty(number):
            return False
        if len(message) > length or start + length > len(self.memory):
            return False
        self.memory[start:start + length] = message + bytes(length - len(message))
        self.memory[ec.REG_SM0 + number * ec.SM_SIZE + ec.SM_OFFSET_STATUS] |= (
            ec.SM_STATUS_MAILBOX_FULL)
        return True

    def clear_mailbox(self, number: int) -> None:
        self.memory[ec.REG_SM0 + number * ec.SM_SIZE + ec.SM_OFFSET_STATUS] &= (
            ~ec.SM_STATUS_MAILBOX_FULL & 0xFF)

    # --- the process data watchdog -----------------------------------------------------------

    def _update_watchdog_period(self) -> None:
        divider = _U16.unpack_from(self.memory, ec.REG_WATCHDOG_DIVIDER)[0]
        time = _U16.unpack_from(self.memory, ec.REG_WATCHDOG_TIME_PROCESS_DATA)[0]
        self._watchdog_period = ec.watchdog_seconds(divider, time)
        if not self._watchdog_period:
            self._watchdog_deadline = None

    def _trigger_watchdog(self) -> None:
        if self._watchdog_period:
            self._watchdog_deadline = self.now + self._watchdog_period
            self.memory[ec.REG_WATCHDOG_STATUS_PROCESS_DATA] |= 0x01

    def check_watchdog(self, now: float) -> None:
        """Expire the process data watchdog when its time passed without a completed output
        buffer (a hardware timer on the chip: it runs on the wall clock)."""
        deadline = self._watchdog_deadline
        if deadline is None or now <= deadline or not self.present:
            return
        self._watchdog_deadline = None
        self.memory[ec.REG_WATCHDOG_STATUS_PROCESS_DATA] &= 0xFE
        counter = ec.REG_WATCHDOG_COUNTER_PROCESS_DATA
        self.memory[counter] = min(0xFF, self.memory[counter] + 1)
        self.firmware.watchdog_expired(self)

    def stop_watchdog(self) -> None:
        self._watchdog_deadline = None

    # --- SYNC0 -------------------------------------------------------------------------------

    def take_sync0(self, t: float) -> bool:
        """The SYNC0 due at `t`, if any, taken by the cyclic unit (the next one set up, the
        status raised, `now` at it) without running the firmware's cycle: the caller runs it
        (the linked line's `run_sync0`, or a segment's batch for all its slaves at once).
        True when one was."""
        if not self.present or not self.dc.take_sync0(t):
            return False
        self.now = t
        return True

    # --- one frame ---------------------------------------------------------------------------

    def process(self, frame: bytearray, view: memoryview,
                datagrams: list[tuple[int, int, int, int]]) -> None:
        """Handle every datagram of a frame as it passes: (command, header offset, data
        offset, data length), offsets into `frame`. Updates addresses, data and working
        counters in place."""
        if not self.present:
            return
        for command, header, data, length in datagrams:
            if ec.Command.LRD <= command <= ec.Command.LRW:
                increment = self._logical(command, _U32.unpack_from(frame, header + 2)[0],
                                          length, view, data)
            elif command in _AUTO_INCREMENT:
                adp = frame[header + 2] | frame[header + 3] << 8
                _U16.pack_into(frame, header + 2, (adp + 1) & 0xFFFF)
                increment = self._physical(command, adp == 0, frame, view, header, data,
                                           length)
            elif command in _CONFIGURED:
                adp = frame[header + 2] | frame[header + 3] << 8
                addressed = adp == self.station_address or (
                    self.memory[ec.REG_DL_CONTROL_ALIAS] & 0x01
                    and adp == _U16.unpack_from(self.memory, ec.REG_STATION_ALIAS)[0])
                increment = self._physical(command, addressed, frame, view, header, data,
                                           length)
            elif command in _BROADCAST:
                adp = frame[header + 2] | frame[header + 3] << 8
                _U16.pack_into(frame, header + 2, (adp + 1) & 0xFFFF)
                increment = self._physical(command, True, frame, view, header, data, length)
            else:
                continue  # NOP and unknown commands pass untouched
            if increment:
                wkc = data + length
                _U16.pack_into(frame, wkc, (_U16.unpack_from(frame, wkc)[0] + increment)
                               & 0xFFFF)
        self.firmware.frame_passed(self)

    def _physical(self, command: int, addressed: bool, frame: bytearray, view: memoryview,
                  header: int, data: int, length: int) -> int:
        address = frame[header + 4] | frame[header + 5] << 8
        kind = _KIND[command]
        if kind == _RMW:  # addressed slave reads, every other slave writes
            if addressed:
                return 1 if self._read(address, length, view, data) else 0
            return 1 if self._write(address, view[data:data + length]) else 0
        if not addressed:
            return 0
        if kind == _READ:
            if command == ec.Command.BRD:
                return 1 if self._read_or(address, length, frame, data) else 0
            return 1 if self._read(address, length, view, data) else 0
        if kind == _WRITE:
            return 1 if self._write(address, view[data:data + length]) else 0
        original = bytes(view[data:data + length])  # read-write: read, then write the original
        if command == ec.Command.BRW:
            read = self._read_or(address, length, frame, data)
        else:
            read = self._read(address, length, view, data)
        written = self._write(address, memoryview(original))
        return (1 if read else 0) + (2 if written else 0)

    def _logical(self, command: int, address: int, length: int, view: memoryview,
                 data: int) -> int:
        """Through the FMMUs: outputs are taken from the frame first, so the firmware's cycle
        runs, then inputs go into the frame (also right for overlapping images)."""
        if self._plan is None:
            return self._logical_checked(command, address, length, view, data)
        end = address + length
        wrote = read = False
        memory = self.view
        writes, reads = self._plan
        if command != ec.Command.LRD:
            for start, stop, physical, completes, watchdog in writes:
                if start < end and address < stop:
                    low = start if start > address else address
                    high = stop if stop < end else end
                    memory[physical + low - start:physical + high - start] = view[
                        data + low - address:data + high - address]
                    wrote = True
                    if completes and high == stop:
                        if watchdog:
                            self._trigger_watchdog()
                        self.firmware.outputs_received(self)
        if command != ec.Command.LWR:
            for start, stop, physical in reads:
                if start < end and address < stop:
                    low = start if start > address else address
                    high = stop if stop < end else end
                    view[data + low - address:data + high - address] = memory[
                        physical + low - start:physical + high - start]
                    read = True
        if command == ec.Command.LRW:
            return (1 if read else 0) + (2 if wrote else 0)
        return 1 if read or wrote else 0

    def _logical_checked(self, command: int, address: int, length: int, view: memoryview,
                         data: int) -> int:
        """The general path: every FMMU access through the sync manager rules."""
        end = address + length
        wrote = read = False
        if command != ec.Command.LRD:
            for start, stop, physical, _, writes in self._fmmus:
                if writes and start < end and address < stop:
                    low, high = max(start, address), min(stop, end)
                    if self._write(physical + low - start,
                                   view[data + low - address:data + high - address]):
                        wrote = True
        if command != ec.Command.LWR:
            for start, stop, physical, reads, _ in self._fmmus:
                if reads and start < end and address < stop:
                    low, high = max(start, address), min(stop, end)
                    if self._read(physical + low - start, high - low, view,
                                  data + low - address):
                        read = True
        if command == ec.Command.LRW:
            return (1 if read else 0) + (2 if wrote else 0)
        return 1 if read or wrote else 0

    # --- memory access with sync manager rules -----------------------------------------------

    def _read(self, address: int, length: int, out: memoryview, offset: int) -> bool:
        end = address + length
        if end > ec.ADDRESS_SPACE:
            return False
        emptied = self._check_sync_managers(address, end, writing=False)
        if emptied is False:
            return False
        if address < dc.DC_END and end > dc.REG_RECEIVE_TIME_PORT0:
            self.dc.before_read(address, end, self.now)
            out[offset:offset + length] = self.view[address:end]
            self.dc.after_read(address, end)
            return True
        out[offset:offset + length] = self.view[address:end]
        if emptied is not None:
            self.clear_mailbox(emptied)
            self.firmware.mailbox_read(self)
        return True

    def _read_or(self, address: int, length: int, frame: bytearray, offset: int) -> bool:
        end = address + length
        if end > ec.ADDRESS_SPACE or self._check_sync_managers(address, end, False) is False:
            return False
        if address < dc.DC_END and end > dc.REG_RECEIVE_TIME_PORT0:
            self.dc.before_read(address, end, self.now)
        memory = self.memory
        for k in range(length):
            frame[offset + k] |= memory[address + k]
        return True

    def _check_sync_managers(self, address: int, end: int, writing: bool) -> int | bool | None:
        """False: a sync manager refuses the access. Otherwise the number of a mailbox-in
        sync manager whose last byte this read takes (it empties), or None."""
        if end <= ec.PROCESS_RAM_START:
            return None
        completes = None
        for number, start, stop, mailbox, master_writes, _ in self._sms:
            if start < end and address < stop:
                if master_writes != writing or number < 0:
                    return False
                if mailbox:
                    full = self.memory[ec.REG_SM0 + number * ec.SM_SIZE
                                       + ec.SM_OFFSET_STATUS] & ec.SM_STATUS_MAILBOX_FULL
                    if writing == bool(full):
                        return False  # writing a full mailbox, reading an empty one
                    if address <= stop - 1 < end:
                        completes = number
        return completes

    def _write(self, address: int, source: memoryview) -> bool:
        end = address + len(source)
        if end > ec.ADDRESS_SPACE:
            return False
        if address < ec.PROCESS_RAM_START:
            registers_end = min(end, ec.PROCESS_RAM_START)
            self._write_registers(address, source[:registers_end - address])
            if end <= ec.PROCESS_RAM_START:
                return True
            source = source[registers_end - address:]
            address = registers_end
        if self._check_sync_managers(address, end, writing=True) is False:
            return False
        self.view[address:end] = source
        for number, start, stop, mailbox, _, watchdog in self._sms:
            if address <= stop - 1 < end:  # the buffer's last byte: the buffer is complete
                if mailbox:
                    self._mailbox_out_complete(number, start, stop)
                else:
                    if watchdog:
                        self._trigger_watchdog()
                    self.firmware.outputs_received(self)
        return True

    def _mailbox_out_complete(self, number: int, start: int, stop: int) -> None:
        status = ec.REG_SM0 + number * ec.SM_SIZE + ec.SM_OFFSET_STATUS
        self.memory[status] |= ec.SM_STATUS_MAILBOX_FULL
        message = bytes(self.view[start:stop])
        self.firmware.mailbox_received(self, message)
        self.memory[status] &= ~ec.SM_STATUS_MAILBOX_FULL & 0xFF  # the PDI has read it

    def _write_registers(self, address: int, source: memoryview) -> None:
        end = address + len(source)
        memory = self.memory
        sms_before = None
        if address < ec.REG_SM0 + ec.SM_SIZE * SM_COUNT and end > ec.REG_SM0:
            sms_before = bytes(memory[ec.REG_SM0:ec.REG_SM0 + ec.SM_SIZE * SM_COUNT])
        for k in range(len(source)):
            mask = _WRITABLE[address + k]
            if mask:
                old = memory[address + k]
                memory[address + k] = (old & ~mask & 0xFF) | (source[k] & mask)
        for low, high in _CLEAR_ON_WRITE:
            if address < high and low < end:
                memory[max(low, address):min(high, end)] = bytes(min(high, end)
                                                                 - max(low, address))
        if sms_before is not None:
            self._sync_managers_written(sms_before)
        if address < ec.REG_FMMU0 + ec.FMMU_SIZE * FMMU_COUNT and end > ec.REG_FMMU0:
            self._rebuild_fmmus()
        if address < ec.REG_WATCHDOG_TIME_PROCESS_DATA + 2 and end > ec.REG_WATCHDOG_DIVIDER:
            self._update_watchdog_period()
        if address < ec.REG_EEPROM_CONTROL + 2 and end > ec.REG_EEPROM_CONTROL:
            self._eeprom_command()
        if address < dc.DC_END and end > dc.REG_RECEIVE_TIME_PORT0:
            self.dc.written(address, end, bytes(source), self.now)
        if address < ec.REG_AL_CONTROL + 2 and end > ec.REG_AL_CONTROL:
            memory[ec.REG_AL_EVENT_REQUEST] |= AL_CONTROL_CHANGED
            self.firmware.al_control(self, _U16.unpack_from(memory, ec.REG_AL_CONTROL)[0])

    def _sync_managers_written(self, before: bytes) -> None:
        """An enabled sync manager keeps its start, length and control; enabling or disabling
        one resets its buffer state; toggling the repeat request asks for the last mailbox
        message again."""
        memory = self.memory
        repeat = []
        for number in range(SM_COUNT):
            base = ec.REG_SM0 + number * ec.SM_SIZE
            old = before[number * ec.SM_SIZE:(number + 1) * ec.SM_SIZE]
            was_enabled = old[ec.SM_OFFSET_ACTIVATE] & ec.SM_ACTIVATE_ENABLE
            if was_enabled:
                memory[base:base + 5] = old[:5]
            activate = memory[base + ec.SM_OFFSET_ACTIVATE]
            if bool(activate & ec.SM_ACTIVATE_ENABLE) != bool(was_enabled):
                memory[base + ec.SM_OFFSET_STATUS] = 0
            elif (activate ^ old[ec.SM_OFFSET_ACTIVATE]) & ec.SM_ACTIVATE_REPEAT:
                repeat.append(number)
        self._rebuild_sync_managers()
        for number in repeat:
            base = ec.REG_SM0 + number * ec.SM_SIZE
            self.firmware.mailbox_repeat(self)
            pdi = memory[base + ec.SM_OFFSET_PDI_CONTROL] & ~ec.SM_PDI_REPEAT_ACK & 0xFF
            memory[base + ec.SM_OFFSET_PDI_CONTROL] = pdi | (
                memory[base + ec.SM_OFFSET_ACTIVATE] & ec.SM_ACTIVATE_REPEAT)

    def _rebuild_sync_managers(self) -> None:
        sms = []
        for number in range(SM_COUNT):
            start, length, control, _, activate, pdi = ec.SYNC_MANAGER.unpack_from(
                self.memory, ec.REG_SM0 + number * ec.SM_SIZE)
            if not activate & ec.SM_ACTIVATE_ENABLE or not length:
                continue
            mailbox = control & ec.SM_CONTROL_MODE_MASK == ec.SM_MODE_MAILBOX
            master_writes = control & ec.SM_CONTROL_DIRECTION_MASK == ec.SM_DIRECTION_WRITE
            # a sync manager the PDI deactivated still guards its area, refusing everything
            key = number if not pdi & ec.SM_PDI_DEACTIVATE else -1 - number
            sms.append((key, start, start + length, mailbox, master_writes,
                        bool(control & ec.SM_CONTROL_WATCHDOG)))
        self._sms = sms
        self._plan_process_data()

    def _rebuild_fmmus(self) -> None:
        fmmus = []
        for number in range(FMMU_COUNT):
            (logical, length, _, _, physical, _, kind, active) = ec.FMMU.unpack_from(
                self.memory, ec.REG_FMMU0 + number * ec.FMMU_SIZE)
            if active & 0x01 and length and kind & (ec.FMMU_READ | ec.FMMU_WRITE):
                fmmus.append((logical, logical + length, physical, bool(kind & ec.FMMU_READ),
                              bool(kind & ec.FMMU_WRITE)))
        self._fmmus = fmmus
        self._plan_process_data()

    def _plan_process_data(self) -> None:
        """The FMMU accesses as plain copies, decided once per configuration change instead
        of per frame: each FMMU of process RAM that lies inside one buffered sync manager (or
        outside all of them) becomes (logical start, end, physical start[, completes the
        buffer, retriggers the watchdog]); accesses the sync manager refuses are left out
        (they count nothing). Anything else (registers, mailboxes, straddling) keeps the
        checked path for every FMMU."""
        writes, reads = [], []
        for start, stop, physical, does_read, does_write in self._fmmus:
            physical_end = physical + stop - start
            if physical < ec.PROCESS_RAM_START or physical_end > ec.ADDRESS_SPACE:
                self._plan = None
                return
            inside = [sm for sm in self._sms if sm[1] < physical_end and physical < sm[2]]
            if len(inside) > 1 or inside and not (inside[0][1] <= physical
                                                  and physical_end <= inside[0][2]):
                self._plan = None
                return
            if inside and inside[0][3]:  # a mailbox behind an FMMU: checked path
                self._plan = None
                return
            sm = inside[0] if inside else None
            if does_write and (sm is None or sm[0] >= 0 and sm[4]):
                completes = sm is not None and physical_end == sm[2]
                writes.append((start, stop, physical, completes, completes and sm[5]))
            if does_read and (sm is None or sm[0] >= 0 and not sm[4]):
                reads.append((start, stop, physical))
        self._plan = (writes, reads)

    # --- the SII EEPROM interface ------------------------------------------------------------

    def _eeprom_command(self) -> None:
        """Run the command just written to 0x0502 at once (the chip's EEPROM is busy for a
        while; a master polls busy and sees it done)."""
        memory = self.memory
        control = _U16.unpack_from(memory, ec.REG_EEPROM_CONTROL)[0]
        command = control & ec.EEPROM_COMMAND_MASK
        status = ec.EEPROM_READ_8_BYTES
        word = _U32.unpack_from(memory, ec.REG_EEPROM_ADDRESS)[0]
        if command == ec.EEPROM_COMMAND_READ:
            start = word * 2
            chunk = bytes(self.eeprom[start:start + 8])
            chunk += b"\xff" * (8 - len(chunk))  # beyond the image: erased cells
            memory[ec.REG_EEPROM_DATA:ec.REG_EEPROM_DATA + 8] = chunk
        elif command == ec.EEPROM_COMMAND_WRITE:
            if not control & ec.EEPROM_WRITE_ENABLE:
                status |= ec.EEPROM_ERROR_WRITE_ENABLE
            elif word * 2 + 2 > len(self.eeprom):
                status |= ec.EEPROM_ERROR_ACKNOWLEDGE
            else:
                self.eeprom[word * 2:word * 2 + 2] = memory[ec.REG_EEPROM_DATA:
                                                            ec.REG_EEPROM_DATA + 2]
        elif command == ec.EEPROM_COMMAND_RELOAD:
            self._reload_configuration()
        elif command:
            status |= ec.EEPROM_ERROR_ACKNOWLEDGE  # two commands at once
        _U16.pack_into(memory, ec.REG_EEPROM_CONTROL, status)


_READ, _WRITE, _READ_WRITE, _RMW = range(4)
_KIND = {
    ec.Command.APRD: _READ, ec.Command.FPRD: _READ, ec.Command.BRD: _READ,
    ec.Command.APWR: _WRITE, ec.Command.FPWR: _WRITE, ec.Command.BWR: _WRITE,
    ec.Command.APRW: _READ_WRITE, ec.Command.FPRW: _READ_WRITE, ec.Command.BRW: _READ_WRITE,
    ec.Command.ARMW: _RMW, ec.Command.FRMW: _RMW,
}
_AUTO_INCREMENT = frozenset((ec.Command.APRD, ec.Command.APWR, ec.Command.APRW,
                             ec.Command.ARMW))
_CONFIGURED = frozenset((ec.Command.FPRD, ec.Command.FPWR, ec.Command.FPRW, ec.Command.FRMW))
_BROADCAST = frozenset((ec.Command.BRD, ec.Command.BWR, ec.Command.BRW))
