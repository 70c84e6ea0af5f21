"""Virtual EtherCAT slaves in a line on one Ethernet interface, each its own CiA 402 drive.

A frame from the master (EtherType 0x88A4) passes every slave in order, as it does through
the ports of real slave controllers, and goes back out of the same interface with the
addresses, data and working counters the slaves left in it. Anything an ESC would not process
(other EtherTypes, broken lengths) is dropped and counted in the first slave's invalid frame
counter (0x0300) instead of being answered, as a frame with a broken checksum would be.

Distributed clocks (`sim_bus.ethercat.dc`): each slave's clock drifts its own stated amount
against the host's monotonic clock, a frame reaches slave k `k` hops after the first, and the
loop wakes for the slaves' SYNC0 events as well as for frames. A frame's time is the kernel's
receive timestamp, so SYNC0 events and frames are handled in the order they happened even when
this process wakes late.
"""

import logging
import math
import select
import socket
import struct
import threading
import time
from collections.abc import Callable, Sequence
from operator import attrgetter
from pathlib import Path

import numpy as np

from protocol import esi_path as shipped_esi_path
from protocol import ethercat as ec
from protocol.esi import EsiDevice, load_esi
from protocol.sii import build_sii
from sim_bus.device import Cia402Device
from sim_bus.ethercat.dc import LineClocks
from sim_bus.ethercat.esc import Esc
from sim_bus.ethercat.firmware import FrameFaults, LineSync, SlaveFirmware
from sim_bus.ethercat.frame_batch import FrameBatch
from sim_bus.line_physics import DriveLine
from sim_bus.priority import RealTimeBudget
from sim_bus.rhythm import AHEAD, Rhythm

log = logging.getLogger(__name__)

POLL = 0.01  # s: how often the loop looks at the stop event and the watchdogs when idle
# the SYNC0 events within this of the line's first are run together (s): well inside the
# outputs' margin before SYNC0 (`sim_bus.ethercat.firmware.OUTPUT_MARGIN`), far wider than the
# spread of synchronized clocks
SYNC0_GATHER = 5e-6
# an answer later than this (s) may have kept the master from a SYNC0 window (`answered`):
# below any SYNC0 cycle a drive runs (125 us is the shortest common one)
MIN_LATE_ANSWER = 100e-6
FRAME_BUFFER = 2048  # a maximum Ethernet frame fits
SO_TIMESTAMPNS = 35  # <asm-generic/socket.h>: receive timestamps (CLOCK_REALTIME, timespec)
_TIMESPEC = struct.Struct("@qq")
# looked at over the whole line after every frame, at C speed (a Python loop over 32 slaves
# cost more than the rest of the frame's bookkeeping)
_MASTER_LOSS = attrgetter("master_loss")
_DELAYED = attrgetter("delay_next_frame")
_REPEATED = attrgetter("repeat_next_frame")
_LOST = attrgetter("lose_next_frame")
# the datagrams that carry process data, through the FMMUs
_LOGICAL = frozenset((ec.Command.LRD, ec.Command.LWR, ec.Command.LRW))


class Segment:
    """The slaves of one line, in the order a frame passes them (position 0 first)."""

    def __init__(self, devices: Sequence[Cia402Device], esi: EsiDevice | None = None):
        self.esi = esi if esi is not None else load_esi(shipped_esi_path())
        self.firmwares = [SlaveFirmware(device, self.esi) for device in devices]
        # whether a slave's fault on a frame's answer waits (`injected_timing`, `frame_lost`):
        # one look a frame, not three passes over every slave (32 slaves: 4.5 us, timeit)
        self.frame_faults = FrameFaults()
        for firmware in self.firmwares:
            firmware.frame_faults = self.frame_faults
        self.escs = []
        for position, firmware in enumerate(self.firmwares):
            esc = Esc(build_sii(self.esi, serial=position + 1), firmware)
            esc.set_link(last=position == len(self.firmwares) - 1)
            esc.dc.place(position, len(self.firmwares))
            firmware.attach(esc)
            self.escs.append(esc)
        self.lock = threading.Lock()  # one frame at a time; Python callers take it too
        self.drives = DriveLine(devices)  # their physics in rows of one set of arrays
        # their distributed clocks in rows of one set of arrays
        self.clocks = LineClocks([esc.memory for esc in self.escs])
        self.clocks.join([esc.dc for esc in self.escs])
        self.clocks.warm()
        # the steady slaves' process data of a frame at once (None: slave by slave, the
        # reference the batch is tested against)
        # their SYNC0 bookkeeping in rows of one set of arrays
        self.sync = LineSync(len(self.firmwares))
        self.sync.join(self.firmwares)
        self.batch: FrameBatch | None = FrameBatch(self.escs, self.firmwares, self.drives,
                                                   self.clocks, self.sync)
        self.frames = 0
        self.dropped = 0
        # no process data watchdog can expire before this time (s): `check_watchdogs` looks
        # at the slaves only after it; every frame may start a watchdog one period later
        self._watch_after = -math.inf
        self._shortest_watchdog = 0.0
        self._alone: list[int] = []  # drives whose master was lost at the last check

    def process(self, frame: bytearray, length: int, now: float) -> bool:
        """Pass one received frame through the slaves, in place; False: no answer."""
        with self.lock:
            batch = self.batch
            answered = pass_frame(self.escs, frame, length, now, batch)
            if batch is None or batch.stale:  # slave by slave: registers may have changed
                self._shortest_watchdog = min((esc._watchdog_period for esc in self.escs
                                               if esc._watchdog_period), default=math.inf)
            self._watch_after = min(self._watch_after, now + self._shortest_watchdog)
        if answered:
            self.frames += 1
        else:
            self.dropped += 1
        return answered

    def renew_draws(self) -> None:
        """A few drives' noise draws renewed (`DriveLine.renew_draws`): once a frame, after
        its answer went."""
        with self.lock:
            self.drives.renew_draws()

    def answered(self, arrival: float, sent: float) -> None:
        """The answer to the frame that arrived at `arrival` left at `sent`: a late one
        (this process stalled) excuses the SYNC0 windows the master could not fill while it
        waited for it (`LineSync.excuse`)."""
        late = sent - arrival
        if late < MIN_LATE_ANSWER or not self.clocks.armed.any():
            return
        armed = np.flatnonzero(self.clocks.armed)[:1]
        self.sync.excuse(arrival, sent, float(self.clocks.cycle_times(armed)[0]))

    def next_sync0(self, now: float) -> float | None:
        """When to run the next SYNC0 events, host time, or None: the slaves' SYNC0 on one
        line fall within microseconds of each other (their system times follow one
        reference), so the loop wakes once for all that fall within SYNC0_GATHER of the
        first, at the last of them, and the batch runs them in one pass. Exact all the same:
        a frame that arrives before is preceded by the SYNC0 events due by its arrival."""
        if not self.clocks.armed.any():  # free run: no SYNC0 anywhere
            return None
        times = self.clocks.upcoming(now)[self._present()]
        first = times.min(initial=math.inf)
        if first == math.inf:
            return None
        return float(times[times <= first + SYNC0_GATHER].max())

    def _present(self) -> np.ndarray:
        return np.fromiter((esc.present for esc in self.escs), dtype=bool,
                           count=len(self.escs))

    def run_sync0(self, now: float) -> int:
        """The SYNC0 events due by `now`, taken for the whole line at once: a slave's pulses
        since the loop last looked are one event at the last of them, as a real ESC's
        latched interrupt (`sim_bus.ethercat.dc`), so a late wake-up catches up in one pass
        (replayed pulse by pulse, the line ran a device cycle per pulse and slave in Python
        after a stall and never caught up); the loop wakes for every pulse when it is not
        late. With the batch, the whole round in one compiled call
        (`FrameBatch.sync0`); slave by slave, `LineClocks.take_due` then each firmware's
        `sync0`. The number of events run."""
        fired = 0
        escs, batch, clocks = self.escs, self.batch, self.clocks
        if not clocks.armed.any():  # free run: no SYNC0 anywhere
            return 0
        with self.lock:
            present = self._present()
            while True:
                if batch is not None:
                    # the batch's pass only when a SYNC0 is due: its look at the drives and
                    # the slaves before it (refresh, steady slaves) at every frame besides
                    # cost talos' DC start its OP (2 of 3 veth starts refused, sync error)
                    if not (clocks.upcoming(now)[present] <= now).any():
                        return fired
                    rows = batch.sync0(now, present)
                else:
                    rows, times = clocks.take_due(now, present)
                    for k, t in zip(rows.tolist(), times.tolist(), strict=True):
                        escs[k].now = t
                        self.firmwares[k].sync0(escs[k])
                if not rows.size:
                    return fired
                fired += rows.size
                if not (clocks.next_host[rows] <= now).any():  # none of them due again
                    return fired

    def check_watchdogs(self, now: float) -> None:
        """The ESCs' process data watchdogs, and the drives' own time once their master is
        gone (`Cia402Device.run_alone`): wall-clock jobs of the real-time loop. Called after
        every frame, so it looks at the slaves only once a deadline can have passed, and
        runs the drives alone only while (and once after) their master is lost: a few
        microseconds a frame instead of a pass over the line."""
        with self.lock:
            if now > self._watch_after:
                if self.batch is not None:
                    self.batch.settle()  # the deadlines of the frames it passed
                earliest = math.inf
                for esc in self.escs:
                    deadline = esc._watchdog_deadline
                    if deadline is not None and now > deadline and esc.present:
                        esc.check_watchdog(now)
                        if self.batch is not None:
                            self.batch.slaves_changed(cycled=False)
                    elif deadline is not None and deadline < earliest:
                        earliest = deadline
                self._watch_after = earliest
            devices = self.drives.devices
            if not self._alone and list(map(_MASTER_LOSS, devices)).count(None) == len(devices):
                return  # every drive has its master
            lost = [k for k, device in enumerate(devices) if device.master_loss is not None]
            # run_alone also forgets its own time once the master is back: one call more
            alone = sorted(set(lost + self._alone))
            for k in alone:
                devices[k].run_alone(now)
            if alone and self.batch is not None:
                self.batch.cycled_elsewhere(alone)
            self._alone = lost

    def report(self) -> list[dict]:
        """Each slave's end state, in line order: EtherCAT state and AL status code, the
        drive's CiA 402 state, brake, master loss, device cycles run, SYNC0 windows its
        outputs missed (DC) and joint position."""
        with self.lock:
            if self.batch is not None:
                self.batch.settle()
            return [{
                "al_status": esc.al_status,
                "al_status_code": esc.memory[ec.REG_AL_STATUS_CODE]
                | esc.memory[ec.REG_AL_STATUS_CODE + 1] << 8,
                "state": firmware.device.state.name,
                "brake_engaged": firmware.device.brake_engaged,
                "master_loss": firmware.device.master_loss,
                "cycles": firmware.cycles,
                "missed_sync0": firmware.missed_sync0,
                "position": firmware.device.plant.position,
            } for esc, firmware in zip(self.escs, self.firmwares, strict=True)]

    def injected_timing(self) -> tuple[float, bool]:
        """Fault injection on the answer to the frame just processed: (hold it this many
        seconds, send it twice)."""
        faults = self.frame_faults
        if not faults.pending:  # nearly always: no slave's frame fault is waiting
            return 0.0, False
        faults.pending = False  # first: a fault injected meanwhile sets it again
        firmwares = self.firmwares
        delay, twice = 0.0, False
        for firmware in firmwares:
            delay = max(delay, firmware.hold())
            twice = twice or firmware.repeat_next_frame
            firmware.repeat_next_frame = False
        if any(map(_LOST, firmwares)):  # waits for a process data frame
            faults.pending = True
        return delay, twice

    def frame_lost(self, frame: bytearray | None = None, length: int = 0) -> bool:
        """Fault injection: whether the process data frame just processed (`frame`, its
        first `length` bytes; None: one known to carry process data) is lost on its way back
        (every slave took it; the master gets nothing). Another frame (a mailbox access, the
        SDO write that injected the fault) passes: the fault is the cycle's."""
        faults, firmwares = self.frame_faults, self.firmwares
        if not faults.pending or not any(map(_LOST, firmwares)):
            return False
        if frame is not None and not any(
                span[0] in _LOGICAL for span in ec.datagram_spans(frame, length) or ()):
            return False
        faults.pending = False  # first: a fault injected meanwhile sets it again
        for firmware in firmwares:
            firmware.lose_next_frame = False
        if any(map(_DELAYED, firmwares)) or any(map(_REPEATED, firmwares)):
            faults.pending = True
        return True


def pass_frame(escs: Sequence[Esc], frame: bytearray, length: int, now: float,
               batch: FrameBatch | None = None) -> bool:
    """One frame through a line of slave controllers, in place; False when it is not a frame
    they process (counted by the first one's invalid frame counter). With `batch` (over
    these `escs`), its steady slaves' process data at once."""
    spans = ec.datagram_spans(frame, length)
    if spans is None:
        if escs and escs[0].present:
            memory = escs[0].memory
            memory[ec.REG_RX_ERROR_COUNTER] = min(0xFF, memory[ec.REG_RX_ERROR_COUNTER] + 1)
        return False
    view = memoryview(frame)
    if batch is None or not (batch.registers(frame, spans)
                             or batch.process(frame, view, spans, now)):
        if batch is not None:
            batch.passed_without(frame, spans)
        routes = _routes(escs, frame, spans)
        for k, esc in enumerate(escs):
            route = spans if routes is None else routes[k]
            # a slave no datagram reaches only posts a waiting mailbox message
            if route or esc.firmware.mail_waiting():
                esc.now = now + esc.dc.hop  # the frame reaches slave k k hops after the first
                esc.process(frame, view, route)
    frame[ec.SOURCE_MAC_OFFSET] |= ec.SOURCE_MAC_PROCESSED_BIT
    return True


_ADDRESSED = frozenset((ec.Command.FPRD, ec.Command.FPWR, ec.Command.FPRW))
_WRITING = frozenset((ec.Command.APWR, ec.Command.APRW, ec.Command.FPWR, ec.Command.FPRW,
                      ec.Command.BWR, ec.Command.BRW, ec.Command.ARMW, ec.Command.FRMW))
# what decides which slave a configured address reaches: station address and alias, and
# the DL control's alias enable
_ADDRESSING = ((ec.REG_STATION_ADDRESS, ec.REG_STATION_ALIAS + 2),
               (ec.REG_DL_CONTROL_ALIAS, ec.REG_DL_CONTROL_ALIAS + 1))


def _routes(escs: Sequence[Esc], frame: bytearray, spans: list) -> list[list] | None:
    """Per slave, the datagrams that can do anything there: a configured-address read or
    write (FPRD/FPWR/FPRW) only at the slave it names, everything else everywhere; None
    when routing saves nothing or the frame itself may readdress a slave. A master's
    state read of a long line (one FPRD per slave in a frame) then costs a datagram per
    slave instead of the whole frame per slave (32 x 32 for TALOS, milliseconds)."""
    if not any(span[0] in _ADDRESSED for span in spans):
        return None
    for command, header, _, length in spans:
        if command in _WRITING:
            ado = frame[header + 4] | frame[header + 5] << 8
            if any(ado < high and low < ado + length for low, high in _ADDRESSING):
                return None
    stations: dict[int, list[int]] = {}
    for k, esc in enumerate(escs):
        if esc.memory[ec.REG_DL_CONTROL_ALIAS] & 0x01:
            return None  # aliases in use: each slave checks for itself
        stations.setdefault(esc.station_address, []).append(k)
    routes: list[list] = [[] for _ in escs]
    for span in spans:
        if span[0] in _ADDRESSED:
            header = span[1]
            for k in stations.get(frame[header + 2] | frame[header + 3] << 8, ()):
                routes[k].append(span)
        else:
            for route in routes:
                route.append(span)
    return routes


def open_socket(interface: str) -> socket.socket:
    """A raw socket receiving the interface's EtherCAT frames (the kernel filters the
    EtherType, so the loop never wakes for other traffic). OSError if it cannot."""
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ec.ETHERTYPE))
    try:
        sock.bind((interface, ec.ETHERTYPE))
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    except OSError:
        sock.close()
        raise
    return sock


def run(sock: socket.socket, segment: Segment, stop: threading.Event) -> None:
    """Answer frames until `stop` is set. A frame the slaves cannot handle is logged and
    dropped; the loop itself never ends on a frame."""
    buffer = bytearray(FRAME_BUFFER)
    view = memoryview(buffer)
    clock = time.monotonic
    # waits in select(), to the microsecond: a socket's own timeout waits in poll(), whose
    # timeout CPython rounds up to the millisecond, so a SYNC0 half a period away ran a whole
    # period later, just when the master's next frame came, and that frame's answer waited
    # behind the SYNC0 pass (0.3 ms asked: 1.14 ms median in poll, 0.45 ms in select)
    sock.setblocking(True)  # select says when a frame is there; sends wait as they would
    readable = (sock,)
    # awake from AHEAD before the master's next frame is due (`sim_bus.rhythm`): asleep,
    # this thread answered each frame 50-150 us late, as long as this host takes to wake it
    rhythm = Rhythm()
    # under the kernel's real-time bandwidth while a master's configuration keeps it busy
    budget = RealTimeBudget(clock())
    while not stop.is_set():
        now = clock()
        budget.spent(now)
        sync0 = segment.next_sync0(now)
        timeout = POLL if sync0 is None else min(POLL, max(0.0, sync0 - now))
        look = rhythm.due - AHEAD - now
        looking = look < timeout
        if looking:
            timeout = max(0.0, look)
        try:
            if not select.select(readable, (), (), timeout)[0]:
                raise BlockingIOError
            length, ancillary, _, _ = sock.recvmsg_into([buffer], _TIMESPEC.size + 32)
        except BlockingIOError:  # no frame: a SYNC0 (or a look at the watchdogs) is due
            now = clock()
            if looking:
                if now > rhythm.due + AHEAD:  # it did not come: sleep until one does
                    rhythm.missed()
                if sync0 is None or now < sync0:
                    continue  # only looking: nothing else is due
            segment.run_sync0(now)
            segment.check_watchdogs(now)
            continue
        now = _arrival(ancillary, clock)
        rhythm.sync(now)
        segment.run_sync0(now)  # the SYNC0 events that came before this frame
        try:
            answer = segment.process(buffer, length, now)
        except Exception:  # a slave's bug must not take the whole line down
            log.exception("frame of %d bytes dropped", length)
            continue
        if answer and segment.frame_lost(buffer, length):
            answer = False  # its slaves ran it; the master waits for it in vain
        if answer:
            delay, twice = segment.injected_timing()
            if delay:
                time.sleep(delay)
            sock.send(view[:length])
            if twice:
                sock.send(view[:length])
            segment.answered(now, clock())
            segment.renew_draws()
        segment.check_watchdogs(now)


def _arrival(ancillary: list, clock: Callable[[], float]) -> float:
    """When the frame arrived, on `clock`: the kernel's timestamp (taken as the frame came
    in, however late this process woke), or now when there is none."""
    now = clock()
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(data) >= _TIMESPEC.size:
            seconds, nanoseconds = _TIMESPEC.unpack_from(data)
            return min(now, now - time.time() + seconds + nanoseconds * 1e-9)
    return now


def serve(interface: str, devices: Sequence[Cia402Device], stop: threading.Event,
          esi_path: str | Path | None = None,
          on_ready: Callable[[Segment], None] | None = None) -> Segment:
    """Run `devices` as a line of EtherCAT slaves on `interface` until `stop` is set (the
    library entry of `sim-bus --bus ethercat:IFACE`); `on_ready(segment)` once the interface
    is open. Raises OSError when the interface cannot be opened and EsiError for a bad ESI
    file; returns the segment for inspection."""
    segment = Segment(devices, load_esi(esi_path) if esi_path is not None else None)
    sock = open_socket(interface)
    if on_ready is not None:
        on_ready(segment)
    try:
        run(sock, segment, stop)
    finally:
        sock.close()
    return segment
