"""Distributed clocks of one slave controller (ET1100 register map, 0x0900-0x09FF): a local
clock that drifts, the system time the master sets up (offset, propagation delay) and keeps
in step (the time control loop fed by writes of the reference clock's time), the receive-time
latches the master measures delays with, and the cyclic unit that fires SYNC0.

Time base: `t`, s, is the host's clock in real time (`time.monotonic`) and the drive time in
lock-step (the linked line's cycles x period): either way it is what "now" means for the
line, and every local clock runs at its own rate against it.

Registers (ETG.1000.4 / ET1100 datasheet, as far as a master reads or writes them):
  0x0900-0x090F  receive time of ports 0-3 (32 bit, local time), latched by a write to 0x0900
  0x0910         system time (64 bit): read = local time + offset; write = compare value
                 (the reference clock's time, fed to the time control loop)
  0x0918         receive time of the ECAT processing unit (64 bit, local time, same latch)
  0x0920         system time offset (64 bit)      0x0928 system time delay (32 bit)
  0x092C         system time difference (32 bit: bit 31 set when the local copy is behind,
                 bits 30-0 the magnitude, ns)
  0x0930         speed counter start (writing it resets the control loop)
  0x0980         cyclic unit control              0x0981 activation (bit 0 cyclic operation,
                 bit 1 SYNC0)
  0x098E         SYNC0 status (bit 0: a SYNC0 came since the last read; cleared by reading)
  0x0990         start time of cyclic operation (64 bit; reads back as the next SYNC0)
  0x09A0         SYNC0 cycle time (32 bit, ns)
"""

import struct
from collections.abc import Sequence

import numpy as np

REG_RECEIVE_TIME_PORT0 = 0x0900
REG_RECEIVE_TIME_PORT1 = 0x0904
REG_SYSTEM_TIME = 0x0910
REG_RECEIVE_TIME_UNIT = 0x0918
REG_SYSTEM_TIME_OFFSET = 0x0920
REG_SYSTEM_TIME_DELAY = 0x0928
REG_SYSTEM_TIME_DIFFERENCE = 0x092C
REG_SPEED_COUNTER_START = 0x0930
REG_CYCLIC_UNIT_CONTROL = 0x0980
REG_SYNC_ACTIVATION = 0x0981
REG_SYNC0_STATUS = 0x098E
REG_START_TIME = 0x0990
REG_SYNC0_CYCLE_TIME = 0x09A0
DC_END = 0x0A00

ACTIVATION_CYCLIC = 0x01
ACTIVATION_SYNC0 = 0x02
FEATURE_DC = 0x0004  # ESC features 0x0008: distributed clocks available
FEATURE_DC_64BIT = 0x0008  # ... with a 64-bit system time
SPEED_COUNTER_START_DEFAULT = 0x1000

# Assumed figures (stated, not measured on a chip):
# the local oscillator's error: a 25 MHz crystal within +-100 ppm is typical; each virtual
# slave gets its own drift in that band (see `slave_drift_ppm`), so the time control loop and
# the master's drift compensation have something to do
DRIFT_SPAN_PPM = 60.0
REFERENCE_DRIFT_PPM = 20.0  # the reference clock against the host: what the master follows
# the time through one slave and its cable to the next, each way (ET1100 with two MII PHYs and
# a short cable: the order of magnitude Beckhoff quotes for a slave's forwarding delay)
HOP_DELAY = 1.0e-6  # s
# the time control loop: a PI on the measured difference, slewing the local clock at most
# MAX_SLEW (the ESC never steps its clock: the system time stays monotonic)
LOOP_GAIN = 1.0e-7  # slew per ns of difference (a 1 us difference slews at 100 ppm)
LOOP_INTEGRAL_GAIN = 2.0e-9  # slew added per compare per ns of difference
MAX_SLEW = 2.0e-4  # 200 ppm: above the worst pair of crystals (2 x 100 ppm)

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_MASK64 = (1 << 64) - 1


def slave_drift_ppm(position: int) -> float:
    """The stated drift of the slave at `position`, ppm: the reference clock (position 0)
    REFERENCE_DRIFT_PPM fast, the others spread over +-DRIFT_SPAN_PPM/2 by a fixed pattern
    (deterministic runs)."""
    if position == 0:
        return REFERENCE_DRIFT_PPM
    return ((position * 37) % 61 - 30) * DRIFT_SPAN_PPM / 60.0


def power_on_local_time(position: int) -> int:
    """ns the slave's local clock shows at t = 0: slaves power up at different moments (a
    fixed 1.7 ms apart here), so offsets are there to compensate."""
    return 1_000_000_000 + position * 1_700_000


class DistributedClock:
    """The DC unit of one ESC, on `memory` (the ESC's register file)."""

    def __init__(self, memory: bytearray):
        self.memory = memory
        self.place(0, 1)
        self.reset()

    def place(self, position: int, line_length: int, hop_delay: float = HOP_DELAY) -> None:
        """Where the slave sits: a frame reaches it `position` hops after the first slave
        and comes back through its port 1 after the slaves behind it (none for the last).
        Its clock is the one of that position (`slave_drift_ppm`, `power_on_local_time`);
        `drift` may be set after (lock-step: 0)."""
        self.drift = slave_drift_ppm(position) * 1e-6
        self._local_at_zero = power_on_local_time(position)
        self.hop = position * hop_delay
        self.return_delay = 2 * (line_length - 1 - position) * hop_delay
        self.last_in_line = position == line_length - 1

    def reset(self) -> None:
        """Power-on: the control loop at rest, no cyclic operation."""
        self._anchor_t = 0.0
        self._correction = 0.0  # ns the control loop has added to the local clock
        self._slew = 0.0
        self._integral = 0.0
        self.next_sync0: int | None = None  # system time of the next SYNC0 (ns)
        self._next_host: float | None = None  # its host time, once worked out (a cache)
        self.sync0_count = 0
        _U16.pack_into(self.memory, REG_SPEED_COUNTER_START, SPEED_COUNTER_START_DEFAULT)

    # --- time --------------------------------------------------------------------------------

    def local_time(self, t: float) -> int:
        """ns on the local clock at host time `t` (its drift and the loop's correction in)."""
        return int(self._local_at_zero + t * 1e9 * (1.0 + self.drift) + self._correction
                   + (t - self._anchor_t) * 1e9 * self._slew)

    def system_time(self, t: float) -> int:
        return (self.local_time(t) + _U64.unpack_from(self.memory, REG_SYSTEM_TIME_OFFSET)[0]
                ) & _MASK64

    def host_time_of(self, system_time: int, t: float) -> float:
        """The host time at which the system time reaches `system_time` (at today's rate)."""
        ahead = _signed64(system_time - self.system_time(t))
        return t + ahead * 1e-9 / (1.0 + self.drift + self._slew)

    # --- registers ----------------------------------------------------------------------------

    def before_read(self, address: int, end: int, t: float) -> None:
        """Bring the registers a read covers up to `t`."""
        memory = self.memory
        if address < REG_SYSTEM_TIME + 8 and end > REG_SYSTEM_TIME:
            _U64.pack_into(memory, REG_SYSTEM_TIME, self.system_time(t))
        if address < REG_START_TIME + 8 and end > REG_START_TIME and self.next_sync0 is not None:
            _U64.pack_into(memory, REG_START_TIME, self.next_sync0)

    def after_read(self, address: int, end: int) -> None:
        if address <= REG_SYNC0_STATUS < end:
            self.memory[REG_SYNC0_STATUS] = 0  # read clears (acknowledge)

    def written(self, address: int, end: int, data: bytes, t: float) -> None:
        """The master wrote `data` at `address` (already in memory where writable)."""
        memory = self.memory
        self._next_host = None  # the clock's rate or offset may change
        if address <= REG_RECEIVE_TIME_PORT0 < end:
            self._latch(t)
        if address <= REG_SYSTEM_TIME < end:
            self._compare(data[REG_SYSTEM_TIME - address:REG_SYSTEM_TIME - address + 8], t)
        if address < REG_SYSTEM_TIME_OFFSET + 8 and end > REG_SYSTEM_TIME_OFFSET or (
                address < REG_SPEED_COUNTER_START + 2 and end > REG_SPEED_COUNTER_START):
            self._settle(t)
            self._slew = self._integral = 0.0
        if address <= REG_SYNC_ACTIVATION < end:
            self._activate(memory[REG_SYNC_ACTIVATION], t)

    def _latch(self, t: float) -> None:
        """A write to 0x0900 passing by: port 0 now, port 1 when the frame comes back from
        the slaves behind (an open port only), the processing unit with port 0."""
        memory = self.memory
        arrival = self.local_time(t)
        _U32.pack_into(memory, REG_RECEIVE_TIME_PORT0, arrival & 0xFFFFFFFF)
        back = 0 if self.last_in_line else self.local_time(t + self.return_delay)
        _U32.pack_into(memory, REG_RECEIVE_TIME_PORT1, back & 0xFFFFFFFF)
        _U64.pack_into(memory, REG_RECEIVE_TIME_UNIT, arrival & _MASK64)

    def _compare(self, data: bytes, t: float) -> None:
        """The time control loop: the written reference time plus this slave's delay against
        its own system time; the difference slews the local clock (a PI, bounded)."""
        delay = _U32.unpack_from(self.memory, REG_SYSTEM_TIME_DELAY)[0]
        own = self.system_time(t)
        if len(data) >= 8:
            difference = _signed64(int.from_bytes(data[:8], "little") + delay - own)
        else:  # a 32-bit write compares the low 32 bits
            difference = _signed32(int.from_bytes(data[:4], "little") + delay - own)
        magnitude = min(abs(difference), 0x7FFFFFFF)
        _U32.pack_into(self.memory, REG_SYSTEM_TIME_DIFFERENCE,
                       magnitude | (0x80000000 if difference > 0 else 0))
        self._settle(t)
        self._integral = _clamp(self._integral + LOOP_INTEGRAL_GAIN * difference, MAX_SLEW)
        self._slew = _clamp(self._integral + LOOP_GAIN * difference, MAX_SLEW)

    def _settle(self, t: float) -> None:
        """Fold the slew so far into the correction before the slew changes."""
        self._correction += (t - self._anchor_t) * 1e9 * self._slew
        self._anchor_t = t

    def _activate(self, activation: int, t: float) -> None:
        """Cyclic operation on with SYNC0: the first pulse at the start time; a start time
        already past never comes (the 64-bit system time does not wrap), the mistake the
        chip does not forgive either."""
        wanted = ACTIVATION_CYCLIC | ACTIVATION_SYNC0
        if activation & wanted != wanted or not self.cycle_time:
            self.next_sync0 = None
            return
        start = _U64.unpack_from(self.memory, REG_START_TIME)[0]
        self.next_sync0 = start if _signed64(start - self.system_time(t)) > 0 else None

    @property
    def cycle_time(self) -> int:
        """SYNC0 cycle time, ns (0: single shot, not supported here)."""
        return _U32.unpack_from(self.memory, REG_SYNC0_CYCLE_TIME)[0]

    @property
    def sync0_active(self) -> bool:
        wanted = ACTIVATION_CYCLIC | ACTIVATION_SYNC0
        return self.memory[REG_SYNC_ACTIVATION] & wanted == wanted

    # --- SYNC0 --------------------------------------------------------------------------------

    def next_sync0_host_time(self, t: float) -> float | None:
        """When (host time) the next SYNC0 fires, seen from `t`; None: none coming."""
        if self.next_sync0 is None:
            return None
        if self._next_host is None:
            self._next_host = self.host_time_of(self.next_sync0, t)
        return self._next_host

    def take_sync0(self, t: float) -> bool:
        """True (once) when a SYNC0 is due at `t`; the next one is then a cycle later."""
        # a few ns of slack: `t` may come from `host_time_of`, rounded through a float
        if self.next_sync0 is None or _signed64(self.system_time(t) - self.next_sync0) < -4:
            return False
        self.next_sync0 = (self.next_sync0 + self.cycle_time) & _MASK64
        self._next_host = None
        self.sync0_count += 1
        self.memory[REG_SYNC0_STATUS] = 0x01
        return True


def compare_line(clocks: Sequence[DistributedClock], data: bytes, times: Sequence[float]
                 ) -> None:
    """The reference clock's time `data` (8 bytes, as an FRMW of 0x0910 carries it) written to
    each of `clocks` at its own host time: `DistributedClock.written` for that write (the
    compare value in 0x0910, the time control loop's step, the difference in 0x092C), for a
    whole line in a few array operations instead of a slave at a time through its ESC (31
    slaves: 56 us of CPU against 176 us, measured with `time.thread_time`). The same
    arithmetic in the same order, so the same results."""
    t = np.array(times, dtype=np.float64)
    local_at_zero = np.array([c._local_at_zero for c in clocks], dtype=np.float64)
    drift = np.array([c.drift for c in clocks], dtype=np.float64)
    correction = np.array([c._correction for c in clocks], dtype=np.float64)
    slew = np.array([c._slew for c in clocks], dtype=np.float64)
    anchor = np.array([c._anchor_t for c in clocks], dtype=np.float64)
    integral = np.array([c._integral for c in clocks], dtype=np.float64)
    offsets = np.array([_U64.unpack_from(c.memory, REG_SYSTEM_TIME_OFFSET)[0] for c in clocks],
                       dtype=np.uint64)
    delays = np.array([_U32.unpack_from(c.memory, REG_SYSTEM_TIME_DELAY)[0] for c in clocks],
                      dtype=np.uint64)
    # local_time: the float sum truncated, as int() does; then the 64-bit system time
    local = (local_at_zero + t * 1e9 * (1.0 + drift) + correction
             + (t - anchor) * 1e9 * slew).astype(np.int64).astype(np.uint64)
    reference = np.uint64(int.from_bytes(data[:8], "little"))
    difference = (reference + delays - (local + offsets)).view(np.int64)  # wraps mod 2**64
    magnitude = np.minimum(np.abs(difference), 0x7FFFFFFF).astype(np.uint32)
    register = (magnitude | np.where(difference > 0, 0x80000000, 0).astype(np.uint32)).tolist()
    correction = correction + (t - anchor) * 1e9 * slew
    # _clamp(value, bound) = max(-bound, min(bound, value))
    integral = np.maximum(-MAX_SLEW, np.minimum(MAX_SLEW, integral
                                                + LOOP_INTEGRAL_GAIN * difference))
    slew = np.maximum(-MAX_SLEW, np.minimum(MAX_SLEW, integral + LOOP_GAIN * difference))
    # the next SYNC0's host time at the new rate, as `host_time_of` works it out at `t` (the
    # loop asks for it next; a clock without one keeps None)
    local = (local_at_zero + t * 1e9 * (1.0 + drift) + correction
             + (t - t) * 1e9 * slew).astype(np.int64).astype(np.uint64)
    following = np.array([c.next_sync0 or 0 for c in clocks], dtype=np.uint64)
    ahead = (following - (local + offsets)).view(np.int64)
    upcoming = (t + ahead * 1e-9 / (1.0 + drift + slew)).tolist()
    values = zip(correction.tolist(), integral.tolist(), slew.tolist(), register, times,
                 upcoming, strict=True)
    compare = bytes(data[:8])
    for clock, (corrected, summed, slewed, difference_register, at, host) in zip(
            clocks, values, strict=True):
        memory = clock.memory
        memory[REG_SYSTEM_TIME:REG_SYSTEM_TIME + 8] = compare
        _U32.pack_into(memory, REG_SYSTEM_TIME_DIFFERENCE, difference_register)
        clock._correction, clock._anchor_t = corrected, at
        clock._integral, clock._slew = summed, slewed
        clock._next_host = None if clock.next_sync0 is None else host


def _signed64(value: int) -> int:
    value &= _MASK64
    return value - (1 << 64) if value >= 1 << 63 else value


def _signed32(value: int) -> int:
    value &= 0xFFFFFFFF
    return value - (1 << 32) if value >= 1 << 31 else value


def _clamp(value: float, bound: float) -> float:
    return max(-bound, min(bound, value))
