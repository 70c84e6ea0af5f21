"""Distributed clocks of one slave controller (ET1100 register map, 0x0900-0x09FF): a local
clock that drifts, the system time the master sets up (offset, propagation delay) and keeps
in step (the time control loop fed by writes of the reference clock's time), the receive-time
latches the master measures delays with, and the cyclic unit that fires SYNC0.

Time base: `t`, s, is the host's clock in real time (`time.monotonic`) and the drive time in
lock-step (the linked line's cycles x period): either way it is what "now" means for the
line, and every local clock runs at its own rate against it.

SYNC0 events: the cyclic unit pulses every cycle; the slave's application takes the pulse as
an interrupt. Pulses that come while the application is busy (here: while the process
running the line is late) collapse into one, as a latched interrupt does on a real ESC: one
event at the last pulse, one run of the application, one count against the sync error
limit (SSC's Sync0_Isr runs once), the pulses themselves all counted in `sync0_count`.
Replayed pulse by pulse, a line that had fallen behind ran a device cycle per missed pulse
and slave in Python and never caught up with real time. A line that is not late wakes for
every pulse, so each is its own event.

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

import math
import struct
from collections.abc import Sequence

import numba
import numpy as np
from numba.typed import List

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


def _row_field(name: str, kind: type = float) -> property:
    """An attribute of one clock kept in its row of the line's array `name`."""
    def get(self) -> float:
        return kind(getattr(self._line, name)[self._row])

    def put(self, value: float) -> None:
        getattr(self._line, name)[self._row] = value

    return property(get, put)


class DistributedClock:
    """The DC unit of one ESC, on `memory` (the ESC's register file). Its state lives in a row
    of a `LineClocks` (its own line of one until a segment `join`s it to the line's), so what
    a cyclic frame or a SYNC0 does to every clock of a line is a few array operations there;
    this class is the slave-by-slave path (registers, set-up) over the same numbers."""

    drift = _row_field("drift")  # the crystal's error, as a fraction (lock-step: 0)
    hop = _row_field("hop")  # s from the first slave's port 0 to this one's
    _local_at_zero = _row_field("local_at_zero")  # ns on the local clock at t = 0
    _correction = _row_field("correction")  # ns the control loop has added
    _slew = _row_field("slew")  # the control loop's rate correction, as a fraction
    _anchor_t = _row_field("anchor")  # host time the slew applies from
    _integral = _row_field("integral")
    sync0_count = _row_field("sync0_count", int)

    def __init__(self, memory: bytearray):
        self.memory = memory
        self._line, self._row = LineClocks([memory]), 0
        self._line.clocks.append(self)
        self.place(0, 1)
        self.reset()

    def join(self, line: "LineClocks", row: int) -> None:
        """Keep this clock's state in row `row` of `line` from now on (as it is now)."""
        for name in LineClocks.FIELDS:
            getattr(line, name)[row] = getattr(self._line, name)[self._row]
        self._line, self._row = line, row

    @property
    def next_sync0(self) -> int | None:
        """System time of the next SYNC0 (ns), None: none coming."""
        return int(self._line.next_sync0[self._row]) if self._line.armed[self._row] else None

    @next_sync0.setter
    def next_sync0(self, value: int | None) -> None:
        self._line.armed[self._row] = value is not None
        self._line.next_sync0[self._row] = 0 if value is None else value & _MASK64

    @property
    def _next_host(self) -> float | None:
        """The next SYNC0's host time, once worked out (a cache; None: not yet)."""
        value = float(self._line.next_host[self._row])
        return None if math.isnan(value) else value

    @_next_host.setter
    def _next_host(self, value: float | None) -> None:
        self._line.next_host[self._row] = math.nan if value is None else value

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
        self._correction = 0.0
        self._slew = 0.0
        self._integral = 0.0
        self.next_sync0 = None
        self._next_host = None
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


@numba.njit(cache=True)
def read_registers(memories, rows: np.ndarray, address: int, size: int) -> np.ndarray:
    """Row n: `size` bytes at `address` of the memory of slave rows[n]."""
    out = np.empty((rows.shape[0], size), dtype=np.uint8)
    for n in range(rows.shape[0]):
        out[n] = memories[rows[n]][address:address + size]
    return out


@numba.njit(cache=True)
def write_registers(memories, rows: np.ndarray, address: int, data: np.ndarray) -> None:
    """Row n of `data` into the memory of slave rows[n] at `address`."""
    size = data.shape[1]
    for n in range(rows.shape[0]):
        memories[rows[n]][address:address + size] = data[n]


class LineClocks:
    """The DC units of a line's slaves, a row each (`DistributedClock.join`), in one set of
    arrays: the cyclic frame's compare (the reference clock's time fed to every other clock),
    the line's next SYNC0 and the SYNC0 events due are each a few array operations and two
    compiled register copies, not a pass over the slaves in Python (31 slaves' compare cost
    176 us through their ESCs, 56 us gathered into arrays and back, measured with
    `time.thread_time`). The registers (offset, delay, cycle time) stay in each ESC's memory,
    read from there at each use, as the per-slave path reads them."""

    FIELDS = ("local_at_zero", "drift", "correction", "slew", "anchor", "integral", "hop",
              "next_sync0", "armed", "next_host", "sync0_count")

    def __init__(self, memories: Sequence[bytearray]):
        count = len(memories)
        self._memories = list(memories)
        self._views = None  # numba's list of the memories, made at the first array operation
        self.clocks: list[DistributedClock] = []  # row k's clock, once joined
        for name in ("local_at_zero", "drift", "correction", "slew", "anchor", "integral",
                     "hop"):
            setattr(self, name, np.zeros(count))
        self.next_sync0 = np.zeros(count, dtype=np.uint64)  # system time, ns
        self.armed = np.zeros(count, dtype=bool)  # a SYNC0 is coming
        self.next_host = np.full(count, math.nan)  # its host time (NaN: not worked out)
        self.sync0_count = np.zeros(count, dtype=np.int64)

    def join(self, clocks: Sequence["DistributedClock"]) -> None:
        """Every clock of the line keeps its state here, in line order, from now on."""
        self.clocks = list(clocks)
        for row, clock in enumerate(clocks):
            clock.join(self, row)

    @property
    def memories(self):
        if self._views is None:
            self._views = List([np.frombuffer(m, np.uint8) for m in self._memories])
        return self._views

    def warm(self) -> None:
        """Load the compiled register copies now, not in the first frame (about 0.1 s)."""
        none = np.zeros(0, dtype=np.int64)
        write_registers(self.memories, none, 0, read_registers(self.memories, none, 0, 1))
        self.compare(none, bytes(8), np.zeros(0))

    def cycle_times(self, rows: np.ndarray) -> np.ndarray:
        """SYNC0 cycle time of each clock of `rows`, s."""
        return read_registers(self.memories, rows, REG_SYNC0_CYCLE_TIME, 4).view(
            "<u4")[:, 0] * 1e-9

    def upcoming(self, t: float) -> np.ndarray:
        """Each clock's next SYNC0 in host time (inf: none coming), seen from `t`; the few not
        worked out since a register write are worked out slave by slave."""
        for k in np.flatnonzero(self.armed & np.isnan(self.next_host)).tolist():
            self.clocks[k].next_sync0_host_time(t)
        return np.where(self.armed, self.next_host, math.inf)

    def take_due(self, now: float, present: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The SYNC0 event of every present clock due by `now`, taken
        (`DistributedClock.take_sync0` for each, at once): (rows, each one's host time). The
        pulses that came since the slave's application last looked are one event, at the
        last of them (see the module's note); the next one is a cycle after it at today's rate,
        the SYNC0 status raised, every pulse counted."""
        times = self.upcoming(now)
        rows = np.flatnonzero(present & (times <= now))
        if not rows.size:
            return rows, times[rows]
        cycles = read_registers(self.memories, rows, REG_SYNC0_CYCLE_TIME, 4).view("<u4")[:, 0]
        step = cycles * 1e-9 / (1.0 + self.drift[rows] + self.slew[rows])
        first = times[rows]
        late = np.where(step > 0, np.floor((now - first) / np.where(step > 0, step, 1.0)),
                        0.0).astype(np.int64)
        at = first + late * step
        self.next_sync0[rows] += cycles.astype(np.uint64) * (late + 1).astype(np.uint64)
        self.next_host[rows] = at + step
        self.sync0_count[rows] += late + 1
        write_registers(self.memories, rows, REG_SYNC0_STATUS,
                        np.ones((rows.size, 1), dtype=np.uint8))
        return rows, at

    def compare(self, rows: np.ndarray, data: bytes, times: np.ndarray) -> None:
        """The reference clock's time `data` (8 bytes, as an FRMW of 0x0910 carries it)
        written to the clocks `rows`, each at its own host time `times`: what
        `DistributedClock.written` does for that write (the compare value in 0x0910, the time
        control loop's step, the difference in 0x092C, the next SYNC0's host time at the new
        rate), in the same arithmetic and order, so the same results, in one compiled call."""
        _compare_rows(self.memories, rows, times, np.frombuffer(bytes(data[:8]), np.uint8),
                      self.local_at_zero, self.drift, self.correction, self.slew, self.anchor,
                      self.integral, self.next_sync0, self.armed, self.next_host)


@numba.njit(cache=True)
def _compare_rows(memories, rows, times, data, local_at_zero, drift, correction, slew, anchor,
                  integral, next_sync0, armed, next_host) -> None:
    """`LineClocks.compare` for each row: `DistributedClock._compare` then the next SYNC0's
    host time (`host_time_of`), on the line's arrays and the ESCs' memories."""
    reference = np.uint64(0)
    for b in range(8):
        reference |= np.uint64(data[b]) << np.uint64(8 * b)
    for n in range(rows.shape[0]):
        k = rows[n]
        t = times[n]
        memory = memories[k]
        offset = np.uint64(0)
        for b in range(8):
            offset |= np.uint64(memory[REG_SYSTEM_TIME_OFFSET + b]) << np.uint64(8 * b)
        delay = np.uint64(0)
        for b in range(4):
            delay |= np.uint64(memory[REG_SYSTEM_TIME_DELAY + b]) << np.uint64(8 * b)
        # local_time: the float sum truncated, as int() does; then the 64-bit system time
        local = np.uint64(np.int64(local_at_zero[k] + t * 1e9 * (1.0 + drift[k])
                                   + correction[k] + (t - anchor[k]) * 1e9 * slew[k]))
        difference = np.int64(reference + delay - (local + offset))  # mod 2**64
        magnitude = min(abs(difference), 0x7FFFFFFF)
        register = magnitude | (0x80000000 if difference > 0 else 0)
        corrected = correction[k] + (t - anchor[k]) * 1e9 * slew[k]
        summed = max(-MAX_SLEW, min(MAX_SLEW, integral[k] + LOOP_INTEGRAL_GAIN * difference))
        slewed = max(-MAX_SLEW, min(MAX_SLEW, summed + LOOP_GAIN * difference))
        correction[k], anchor[k], integral[k], slew[k] = corrected, t, summed, slewed
        if armed[k]:
            # the next SYNC0's host time at the new rate, as `host_time_of` works it out at t
            local = np.uint64(np.int64(local_at_zero[k] + t * 1e9 * (1.0 + drift[k])
                                       + corrected + (t - t) * 1e9 * slewed))
            ahead = np.int64(next_sync0[k] - (local + offset))
            next_host[k] = t + ahead * 1e-9 / (1.0 + drift[k] + slewed)
        else:
            next_host[k] = np.nan
        for b in range(8):
            memory[REG_SYSTEM_TIME + b] = data[b]
        for b in range(4):
            memory[REG_SYSTEM_TIME_DIFFERENCE + b] = (register >> (8 * b)) & 0xFF


def _signed64(value: int) -> int:
    value &= _MASK64
    return value - (1 << 64) if value >= 1 << 63 else value


def _signed32(value: int) -> int:
    value &= 0xFFFFFFFF
    return value - (1 << 32) if value >= 1 << 31 else value


def _clamp(value: float, bound: float) -> float:
    return max(-bound, min(bound, value))
