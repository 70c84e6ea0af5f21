"""One EtherCAT line seen from the master (pysoem, i.e. SOEM): bring-up of every slave on it,
identity checked against the ESI, the EtherCAT state machine with refusals reported by AL
status code name, and the cyclic frame that carries every slave's process data at once.

A line has one master by construction (the master's port is the line's only way in), so the
slaves on it are shared by the transports of every joint: `driver.ethercat_transport` gives
each joint its slave, and the first `exchange` of a cycle sends the one frame of that cycle.

Working counter: the frame comes back with every slave's contribution (+2 for the outputs it
took, +1 for the inputs it gave); anything less means a slave is gone or left OP. The master
stops the line at once (sticky failure), reads every slave's AL status first and names the
slaves that are not in OP, with their state and AL status code in words (SOEM's simple_test
does the same with ecx_readstate). A slave counts as not answering only when the line's group
read of AL states, tried several times apart, and then a read of its own went unanswered
(`_read_states`): SOEM's group read leaves every slave whose answer came after its 6 ms at
state 0, and a slave host busy stopping 32 drives after a sync error answers later than that
(talos_32 in DC: 32 slaves sitting in SAFE-OP reported as "did not answer (gone from the
line?)", the working counter 32 of 96).

A slave that leaves OP on its own (a sync error, a local restart) keeps answering the cyclic
frame: an ESC counts the process data it moves whatever the application's state, so the
working counter stays whole. The master therefore reads every slave's AL status every
STATE_CHECK_FRAMES cycles (one broadcast read while all are in OP), and whenever a drive
reports a fault, so the slave that left is named with its AL status code before its drive's
reaction (EMCY 0xA000) is taken for the cause. Slaves carry their joint's name where the
robot gives one (`names`).
"""

import contextlib
import logging
import math
import os
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pysoem

from driver.clock import DriveClock, WallClock
from driver.ethercat_dc import DcLine
from driver.interface import DriveError, DriveLost, ProfileError, SampleLost
from protocol import ethercat as ec
from protocol.esi import EsiDevice

log = logging.getLogger(__name__)

STATE_TIMEOUT_US = 2_000_000  # SOEM's EC_TIMEOUTSTATE: what a state change may take
OP_FRAMES = 200  # frames sent after the OP request before giving up (OP comes with outputs)
DEFAULT_WATCHDOG = 0.1  # s: the ESC's reset value (ETG.1000.4: 1000 x 100 us)
KEEP_ALIVE = 0.02  # s: a fifth of the ESC's default watchdog
KEEPER_SWITCH_SHARE = 0.25  # DC: the interpreter's switch interval at most this share of a period
SCAN_RETRY = 0.1  # s between two scans of a line that did not answer right
SYNC_MODES = ("free_run", "dc")
DEFAULT_DC_PERIOD = 1e-3  # s: SYNC0 period when no transport said (start sets it)
DC_OP_TIMEOUT = 1.0  # s for the slaves to take OP at a SYNC0 (the first comes 100 ms after set-up)
DC_OP_CHECK_FRAMES = 8  # DC: frames between two reads of the slaves' states on the way to OP
DC_SETTLE_FRAMES = 2  # DC: frames before the first cycle (see `settle`)
PAST_SYNC0 = 50e-6  # s: DC, a frame's SYNC0 surely run by the slaves this long after it
# cycles between two reads of the slaves' AL status: a slave out of OP is named within 10 ms
# at 1 kHz, at the cost of one broadcast read in ten cycles (counted in cycles, so lock-step
# finds it in the same cycle every run)
STATE_CHECK_FRAMES = 10
# a failed line's AL states: the group read tried this many times, this long apart (real
# time), before each slave it left without an answer is read on its own (SOEM's group read
# waits 6 ms; a slave host stopping 32 drives fell 60 ms behind, its late answers dropped)
STATE_READ_TRIES = 3
STATE_READ_PAUSE = 0.05  # s
STATE_READ_TIMEOUT_US = 20_000
REG_AL_STATUS_SPAN = 6  # AL status (0x0130), reserved, AL status code (0x0134): one read
# How long SOEM waits for an acyclic frame to come back (its EC_TIMEOUTRET, process-wide):
# while the line is configured, and from OP on. Configuring, a frame later than that is the
# worst case: the slave still answers the mailbox request it carried, SOEM's next SDO read of
# the same object takes that stale answer for its own (it checks the index, not the
# subindex), config_map sums a PDO entry's wrong length, and the slave refuses SAFE-OP with
# 0x001E (measured: talos_32's virtual line in another process on a loaded host, 2 of 8
# starts). So while nothing is cyclic SOEM waits as for a slow link (its EC_TIMEOUTSAFE);
# in OP its default again, so a cycle's state read never waits longer than two periods.
CONFIGURING_RETURN_TIMEOUT_US = 20_000
OPERATIONAL_RETURN_TIMEOUT_US = 2_000
# In OP on the wall clock, a cycle's frame not back within this many periods is lost: the
# cycle goes on without its sample, as SOEM's simple_test does (it waits EC_TIMEOUTRET, 2 ms,
# for a 1 ms cycle's frame and counts the working counter; its check thread recovers
# slaves). Waiting the drives' response timeout instead (100 ms, their process data
# watchdog) held a line whose frame a bit error had eaten for as long as its drives forgive
# a silent master, and then failed it. On drive time a frame is never late, only missing.
LOST_AFTER_PERIODS = 2
# How long frames may stay lost (none came back) before the line fails; the drives hold the
# outputs they had meanwhile. In real time: as long as the drives themselves hold without a
# frame, their process data watchdog (`watchdog`, the ESC's 100 ms unless given) since the
# last whole frame; past it a free-running drive has stopped itself, and the line fails
# naming every slave. Failing sooner stops a robot whose drives still hold: at the third
# frame lost in a row (6 ms at 1 kHz, the rule before) 3 of 10 one-minute starts of
# talos_32 over a veth (free run) failed on a host that held the virtual line's process for
# a few ms, a stall its drives forgave. A DC drive gives up sooner on its own (it counts each
# SYNC0 window without outputs and leaves OP past its sync error limit: talos_32.toml's 9 at
# the fourth empty window in a row), and the first frame back says so. On drive time a frame
# is never late: one that does not come back within the response timeout is missing, and
# the line fails at the (LOST_FRAMES_IN_A_ROW + 1)th in a row. A frame that comes back short
# of its working counter is no lost frame: a slave in it did not take its part (left OP,
# gone), and the line fails at once, naming it.
LOST_FRAMES_IN_A_ROW = 2


class LineFailure(DriveError):
    """What particular slaves of the line did (0-based `positions`, in the order the message
    names them), so a drive group can name their joints: a state change refused."""

    def __init__(self, message: str, positions: tuple[int, ...] = ()):
        super().__init__(message)
        self.positions = positions


class LineLost(LineFailure, DriveLost):
    """The line stopped mid-run: a frame short of its working counter, or slaves out of OP."""


class LineSilent(LineLost):
    """Nothing on the line answers any more: frames stayed lost past what the drives forgive.
    A CoE access then fails at once (`driver.ethercat_transport`) instead of waiting out its
    mailbox timeouts slave by slave: the quick stop and the close of talos_32 on a line whose
    slaves were gone took 7 s so."""


class EthercatMaster:
    """The slaves on `interface`, described by `esi` (every slave must be that device).

    `clock` (`driver.clock`, made by `clock_for`; default the wall clock): the line's time,
    which the master waits on (DC start-up, settling) and which its cyclic frames advance
    (drive time: the count of the line's frames x period). On drive time the slaves' process
    data watchdog (a wall-clock timer in each ESC) is switched off (0x0420 = 0), because the
    host may pause for any wall time between two cycles; the master's own check, the working
    counter of every frame, counts cycles. On the wall clock the watchdog is on (the ESC's
    100 ms, or `watchdog` s; written, never assumed), so the slaves stop their drives when
    this master dies.

    `open_master` makes the pysoem master (by default SOEM on the interface; a line of
    virtual slaves in this process for `--sim`: `sim_bus.ethercat.linked.LinkedMaster`).

    `sync`: "free_run" (SM-synchronous: each slave runs its cycle as the frame's outputs
    arrive) or "dc" (distributed clocks: delays and offsets set up, SYNC0 every period, the
    drift compensated by every frame and this master's wake-up following the reference clock;
    `driver.ethercat_dc`). The period comes from the transports' `start`.
    """

    def __init__(self, interface: str, esi: EsiDevice, *,
                 clock: WallClock | DriveClock | None = None,
                 response_timeout: float | None = None, watchdog: float | None = None,
                 open_master: Callable[[], Any] = pysoem.Master, sync: str = "free_run"):
        if sync not in SYNC_MODES:
            raise ValueError(f"EtherCAT sync {sync!r}: expected one of {', '.join(SYNC_MODES)}")
        self.interface = interface
        self.sync = sync
        self.period: float | None = None  # s, set by the transports' start
        self.dc: DcLine | None = None
        self._open_master = open_master
        self.esi = esi
        self.clock = clock if clock is not None else WallClock()
        if response_timeout is None:
            response_timeout = self.clock.response_timeout
        self.response_timeout_us = int(response_timeout * 1e6)
        # us the cycle's frame is waited for (`_operational`: LOST_AFTER_PERIODS in real time)
        self.frame_timeout_us = self.response_timeout_us
        self.lost_frames = 0  # cyclic frames that did not come back (ridden through)
        self.last_loss: SampleLost | None = None  # the last, raised for cycle `last_loss_at`
        self.last_loss_at = 0
        self._lost_in_a_row = 0
        # time.monotonic() of the last whole process data frame: in real time the line rides
        # through lost frames until the drives' watchdog has passed since (`_rides_through`)
        self._whole_at = 0.0
        self.watchdog = watchdog
        self.master: pysoem.Master | None = None
        self.slaves: list = []
        self.names: dict[int, str] = {}  # position -> joint name, where the robot gives one
        self.frames = 0  # cyclic frames sent since the line went operational
        self.failure: DriveError | None = None
        self.operational = False
        self.mapped = False  # the process image exists (config_map done)
        self._released: set[int] = set()  # positions taken out of the cycle on purpose
        # DC: positions released while the line is in OP, kept in it until it goes down as a
        # whole (`release`, `close_line`)
        self._leaving: set[int] = set()
        self._expected_wkc = 0
        self._last_frame = 0.0  # time.monotonic() of the last process data frame
        # position -> (ready for OP, stage its outputs)
        self._claimed: dict[int, tuple[Callable[[], bool], Callable[[], None]]] = {}
        # one user of SOEM at a time: the cycle, CoE accesses and the keeper
        self.lock = threading.RLock()
        # SOEM's sockets, polled for frames in OP (`_poll_for_frames`), and how deep the
        # accesses that wait for theirs asleep are nested (`acyclic`)
        self._polled: list[int] = []
        self._asleep_depth = 0
        self._keeper_stop: threading.Event | None = None
        self._sent_at = 0.0  # time.monotonic() the last process data frame went out
        self._cycle_sent_at = 0.0  # ... the last cycle's own frame (DC: the keeper's look)

    # --- bring-up ----------------------------------------------------------------------------

    def claim(self, position: int, ready: Callable[[], bool],
              stage: Callable[[], None]) -> None:
        """A transport takes the slave at `position`: `ready()` says when its process data is
        mapped (the line goes to OP once every claimed slave is ready), `stage()` puts its
        outputs into the process image (called once the image exists, before the first
        frame, so a drive enabled before OP stays enabled)."""
        if position in self._claimed:
            raise ValueError(f"slave {position} on {self.interface} is already in use")
        self._claimed[position] = (ready, stage)

    def unclaim(self, position: int) -> None:
        """A transport is done with its slave; the last one closes the line."""
        self._claimed.pop(position, None)
        if not self._claimed:
            self.close_line()

    def scan(self, timeout: float) -> None:
        """INIT -> PRE-OP for the whole line (SOEM's config_init: addresses, SII, mailbox),
        each slave's identity checked against the ESI. Again after a failure: a fresh start.
        A line that does not answer, or answers with an identity that is not the ESI's, is
        scanned again until `timeout` s have passed (SOEM gives each register access a few
        ms: a busy slave host can miss one), then refused."""
        deadline = time.monotonic() + timeout
        while True:
            problem = self._scan_once()
            if problem is None:
                break
            if time.monotonic() > deadline:
                raise problem
            time.sleep(SCAN_RETRY)
        self._require_state(pysoem.PREOP_STATE, "PRE_OP")
        self.failure = None
        self._released.clear()
        self._leaving.clear()
        self.frames = 0

    def _scan_once(self) -> DriveError | None:
        self.close_line()
        pysoem.settings.timeouts.ret = CONFIGURING_RETURN_TIMEOUT_US
        master = self._open_master()
        try:
            master.open(self.interface)
        except ConnectionError as exc:
            raise DriveLost(f"EtherCAT {self.interface}: cannot open the interface "
                            f"({_why_not_open(self.interface, exc)})") from None
        self.master = master
        if master.config_init() <= 0:
            return DriveLost(f"EtherCAT {self.interface}: no slave answers (line unplugged or "
                             "powered off?)")
        self.slaves = list(master.slaves)
        for position, slave in enumerate(self.slaves):
            identity = (slave.man, slave.id, slave.rev)
            if identity != self.esi.identity:
                return ProfileError(
                    f"EtherCAT {self.interface} slave {position} ({slave.name!r}): SII identity "
                    f"vendor 0x{identity[0]:08X} product 0x{identity[1]:08X} revision "
                    f"0x{identity[2]:08X}, the ESI describes vendor 0x{self.esi.vendor_id:08X} "
                    f"product 0x{self.esi.product_code:08X} revision 0x{self.esi.revision:08X} "
                    f"({self.esi.name})")
        return None

    def slave(self, position: int):
        if not 0 <= position < len(self.slaves):
            raise DriveLost(f"EtherCAT {self.interface}: no slave at position {position} "
                            f"({len(self.slaves)} found, positions count from 0)")
        return self.slaves[position]

    def all_ready(self) -> bool:
        return all(ready() for ready, _ in self._claimed.values())

    def go_operational(self) -> None:
        """PRE-OP -> SAFE-OP -> OP for the whole line: the process data image (SOEM's
        config_map from each slave's CoE assignment), then the OP request and frames until
        every slave is operational (a slave enters OP with its first valid outputs)."""
        if self.operational:
            return
        with self.lock:
            self._go_operational()

    def _go_operational(self) -> None:
        master = self.master
        if not self.mapped:
            try:
                # written in real time too, never left as found: an earlier drive-time master
                # (killed, or one that never closed) may have switched it off, and a slave
                # without it keeps its drive enabled when this master dies
                milliseconds = 0.0 if not self.clock.runs_alone else (
                    self.watchdog if self.watchdog is not None else DEFAULT_WATCHDOG) * 1e3
                for slave in self.slaves:
                    slave.set_watchdog("processdata", milliseconds)
                master.config_map()
            except pysoem.ConfigMapError as exc:
                raise DriveError(f"EtherCAT {self.interface}: reading the PDO assignment "
                                 f"failed: {_errors(exc.error_list)}") from None
            except (pysoem.WkcError, AttributeError) as exc:
                raise DriveError(f"EtherCAT {self.interface}: setting the process data "
                                 f"watchdog failed: {exc!r}") from None
            self.mapped = True
        for _, stage in self._claimed.values():
            stage()
        self._require_state(pysoem.SAFEOP_STATE, "SAFE_OP")
        self._expected_wkc = master.expected_wkc
        if self.sync == "dc":
            self.dc = DcLine(self.interface, self.period or DEFAULT_DC_PERIOD)
            self.dc.configure(master, self.slaves)
            log.info("%s", self.dc.describe())
        master.state = pysoem.OP_STATE
        master.write_state()
        if self.dc is not None:
            self._dc_to_operational()
            return
        for _ in range(OP_FRAMES):
            master.send_processdata()
            master.receive_processdata(self.response_timeout_us)
            if master.state_check(pysoem.OP_STATE, 1000) == pysoem.OP_STATE:
                self._operational()
                return
        self._require_state(pysoem.OP_STATE, "OP")

    def _dc_to_operational(self) -> None:
        """DC: a frame every period until every slave took OP at a SYNC0 with outputs in its
        window (the first SYNC0 comes 100 ms after the set-up), the frames already placed in
        the reference clock's cycle. On drive time a frame is a period of it."""
        master, clock = self.master, self.clock
        period = self.dc.period_ns * 1e-9
        wake = clock.now()
        deadline, frames = wake + DC_OP_TIMEOUT, 0
        for _ in range(int(DC_OP_TIMEOUT / period)):
            self._sent_at = time.monotonic()
            master.send_processdata()
            master.receive_processdata(self.response_timeout_us)
            self.dc.observe(master.dc_time, self._sent_at)
            # one read every few frames (state_check would sleep a millisecond when not there
            # yet, and a long line's states take a few round trips: a frame a period is what
            # SYNC0 needs)
            frames += 1
            if frames % DC_OP_CHECK_FRAMES == 0 and master.read_state() == pysoem.OP_STATE:
                self._operational()
                return
            if clock.now() > deadline:
                break
            wake += period + self.dc.take_trim()
            clock.sleep_until(wake)
        self._require_state(pysoem.OP_STATE, "OP")

    def _operational(self) -> None:
        """Every slave in OP: SOEM's operational wait, frames polled for in real time
        (`_poll_for_frames`), and the keeper."""
        self.operational = True
        pysoem.settings.timeouts.ret = OPERATIONAL_RETURN_TIMEOUT_US
        if self.clock.runs_alone:
            self._polled = _packet_sockets(self.interface)
            _poll_for_frames(self._polled)
            period = self.dc.period_ns * 1e-9 if self.dc is not None else self.period
            if period:
                self.frame_timeout_us = min(self.response_timeout_us,
                                            round(LOST_AFTER_PERIODS * period * 1e6))
        self._last_frame = self._whole_at = time.monotonic()
        self._start_keeper()

    def settle(self) -> None:
        """Before the first cycle, once the drives are enabled. DC: the slaves take outputs
        and sample inputs at SYNC0, so the enable sequence (acyclic) reaches them with the
        next frame and shows in the inputs of the one after: those frames go first (not
        counted as cycles), so the first cycle's sample shows the enabled drives."""
        if self.dc is None:
            return
        for _ in range(DC_SETTLE_FRAMES):
            self.pass_image()

    def pass_image(self) -> None:
        """One process data frame outside the cycle, by which `driver.ethercat_transport`
        reads and writes what the process data carries (the enable sequence's statusword and
        controlword) from OP on. Free run: the slaves take its outputs and run their cycle
        as it passes, and the next frame reads what they made of them; on drive time the
        frame is a period of it, as a cycle's is. DC: the SYNC0 after it takes its outputs
        and samples the inputs the next one reads. In real time the DC frame goes at the
        cycle's own phase of the reference clock (`DcLine.next_frame`) and the line's lock
        is held for the frame only: a frame sent whenever the caller came by landed late in
        a window as often as early, and one held back by the lock over a period's sleep
        kept the keeper from its window (the second of talos_32's DC starts out with 0x001A
        before its first cycle)."""
        if self.dc is None:
            with self.acyclic():
                self._frame()
                if self.period is not None:
                    self.clock.advance(self.period)  # drive time: frames x period
            return
        if not self.clock.runs_alone:
            with self.lock:
                self._frame()
            self.clock.sleep_until(self.clock.now() + self.dc.period_ns * 1e-9)
            return
        send, sync0 = self.dc.next_frame(time.monotonic())
        self.clock.sleep_until(send)
        with self.lock:
            self._frame()
        self.clock.sleep_until(max(sync0, self._last_frame) + PAST_SYNC0)

    def last_frame(self) -> bool:
        """After the line failed (one slave left OP, or a frame came back short): one frame
        more, which takes the staged outputs (a quick stop, the disable on close) to the
        slaves still in OP, best effort; whether any slave took it. The failure stays: the
        cycle is over. A drive refuses an SDO write of its controlword from SAFE-OP on, so
        this frame is how the drives the failure spared are stopped before their own
        watchdog stops them; a silent line gets none."""
        if not self.operational or self.master is None or isinstance(self.failure, LineSilent):
            return False
        with self.acyclic():
            wkc = self._send_and_receive()
            if self.period is not None:
                self.clock.advance(self.period)  # drive time: frames x period
        return wkc > 0

    def clock_trim(self) -> float:
        """s to add to the next period of the cycle's clock (DC: follow the reference)."""
        return self.dc.take_trim() if self.dc is not None else 0.0

    def request_state(self, state: int) -> None:
        """Ask every slave for `state` and wait for it (DriveError naming the refusals)."""
        with self.lock:
            self.master.state = state
            self.master.write_state()
            self._require_state(state, ec.al_state_name(state))

    def _require_state(self, state: int, name: str) -> None:
        """Wait for every slave to reach `state`; DriveError naming each that did not, with
        its state and AL status code by name."""
        master = self.master
        if master.state_check(state, STATE_TIMEOUT_US) == state:
            return
        states = self._read_states(range(len(self.slaves)))
        stuck = [position for position, status in states.items()
                 if status is None or status[0] & ec.AL_STATE_MASK != state]
        raise LineFailure(f"EtherCAT {self.interface}: {name} refused: "
                          + "; ".join(self._describe(position, states[position])
                                      for position in stuck), tuple(stuck))

    def label(self, position: int) -> str:
        """'slave 3 (arm_left_4_joint)', or 'slave 3' where no joint name is known."""
        name = self.names.get(position)
        return f"slave {position}" + (f" ({name})" if name else "")

    def _read_states(self, positions, thorough: bool = True
                     ) -> dict[int, tuple[int, int] | None]:
        """(AL status, AL status code) of each slave of `positions`, read now by the line's
        group read (SOEM's ecx_readstate, which leaves a slave whose answer did not come at
        state 0); None for a slave that did not answer. `thorough` (the line has failed:
        what it says must be right): the group read tried STATE_READ_TRIES times,
        STATE_READ_PAUSE apart in real time, then each slave still without an answer read
        on its own; a slave counts as not answering only then."""
        states: dict[int, tuple[int, int] | None] = dict.fromkeys(positions)
        for attempt in range(STATE_READ_TRIES if thorough else 1):
            if attempt and self.clock.runs_alone:
                time.sleep(STATE_READ_PAUSE)
            try:
                self.master.read_state()
            except pysoem.WkcError:
                continue
            for position in states:
                slave = self.slaves[position]
                if states[position] is None and slave.state & ec.AL_STATE_MASK:
                    states[position] = (slave.state, slave.al_status)
            if None not in states.values():
                return states
        if thorough:
            for position, status in states.items():
                if status is None:
                    states[position] = _read_state_of(self.slaves[position])
        return states

    def _describe(self, position: int, status: tuple[int, int] | None) -> str:
        """The slave's state and AL status code in words, as `_read_states` read them; None:
        it answered none of the reads."""
        if status is None:
            return (f"{self.label(position)} did not answer (no answer to "
                    f"{STATE_READ_TRIES} reads of the line's AL states nor to one of its own: "
                    "gone from the line?)")
        state, code = status
        text = f"{self.label(position)} in {ec.al_state_name(state)}"
        if state & ec.AL_ERROR or code:
            text += f", AL status code {ec.al_status_name(code)}"
        return text

    # --- the cycle ---------------------------------------------------------------------------

    def cycle(self) -> None:
        """Send the one frame of this cycle and check its working counter (DC: and the
        master's offset from the reference clock); every STATE_CHECK_FRAMES cycles, every
        slave's AL status too. A frame that did not come back raises SampleLost while the
        line rides through it (`LOST_FRAMES_IN_A_ROW`: in real time up to the drives'
        watchdog)."""
        asked = time.monotonic()
        with self.lock:
            self.frames += 1
            whole = self._frame()
            if self.period is not None:
                self.clock.advance(self.period)  # drive time: frames x period
            if not whole:  # no reference time read, no states: the next frame's
                self._cycle_sent_at = self._sent_at
                self.last_loss_at = self.frames
                self.last_loss = SampleLost(
                    f"EtherCAT {self.interface}: the frame of cycle {self.frames} did not come "
                    f"back within {self.frame_timeout_us / 1e3:g} ms ({self._lost_in_a_row} "
                    f"in a row; {self._fails_at()}): the drives hold their last command")
                if self._lost_in_a_row == 1:  # once for a run of lost frames, not each
                    log.warning("%s", self.last_loss)
                raise self.last_loss
            if self.dc is not None:
                self.dc.observe(self.master.dc_time, self._sent_at)
                self._cycle_sent_at = self._sent_at
                # where the cycle's exchange went: waiting for the line (the keeper's or a
                # CoE access's frame), or the frame's round trip
                self.dc.exchanged(self._sent_at - asked, self._last_frame - self._sent_at)
            if self.frames % STATE_CHECK_FRAMES == 0:
                self._check_states()

    def check_states(self) -> None:
        """Read every slave's AL status now (a drive reported a fault: its slave may have left
        OP, which is then the cause to name); LineFailure naming each slave in the cycle that
        is not in OP. Nothing to do before OP or once the line has failed."""
        with self.lock:
            if self.failure is not None:
                raise self.failure
            if self.operational:
                self._check_states()

    def _check_states(self) -> None:
        """One group read, in the cycle: a slave that answered it out of OP fails the line;
        one that did not answer is left to the next frame's working counter (a read that
        came back late is no reason to stop a running line)."""
        states = self._read_states([position for position in range(len(self.slaves))
                                    if position not in self._released], thorough=False)
        out = [position for position, status in states.items()
               if status is not None and status[0] & ec.AL_STATE_MASK != pysoem.OP_STATE]
        if out:
            self.failure = LineLost(
                f"EtherCAT {self.interface}: left OP by cycle {self.frames}: "
                + "; ".join(self._describe(position, states[position]) for position in out),
                tuple(out))
            log.error("%s", self.failure)
            raise self.failure

    def _start_keeper(self) -> None:
        """Real time: from OP on, a thread of the line's own sends a frame whenever the
        cycle has sent none for KEEP_ALIVE s, so nothing the controller does (the cold solve
        of 32 joints, an enable sequence, a garbage collection, a stalled cycle) starves the
        slaves' watchdog: at worst the drives hold the last command a little longer. A real
        master (SOEM's examples, ros2_control's EtherCAT drivers) keeps its own cyclic thread
        for the same reason. On drive time there is none: a frame is a cycle of it there."""
        if not self.clock.runs_alone or self._keeper_stop is not None:
            return
        # the keeper is a Python thread: while another holds the interpreter (the cold solve,
        # a garbage collection) it waits for the switch interval, 5 ms by default, longer
        # than the three SYNC0 windows a slave forgives on distributed clocks
        if self.dc is not None:
            sys.setswitchinterval(min(sys.getswitchinterval(),
                                      KEEPER_SWITCH_SHARE * self.dc.period_ns * 1e-9))
        stop = self._keeper_stop = threading.Event()
        threading.Thread(target=self._keep if self.dc is None else self._keep_windows,
                         args=(stop,), daemon=True,
                         name=f"ethercat-keeper-{self.interface}").start()

    def _keep(self, stop: threading.Event) -> None:
        _above_the_cycle()
        while not stop.wait(KEEP_ALIVE / 2):
            if not self._keep_once(stop):
                return

    def _keep_once(self, stop: threading.Event,
                   window: tuple[float, float] | None = None) -> bool:
        """One look of the keeper (DC: at `window`), under the line's lock; False: it ends."""
        with self.lock:
            if stop.is_set():
                return False
            try:
                self.keep_alive(window)
            except DriveError:
                return False  # kept in self.failure: the next cycle raises it, naming the slave
            except pysoem.NetworkInterfaceNotOpenError:
                return False  # the interface went away under it: the next cycle says so
        return True

    @contextlib.contextmanager
    def acyclic(self) -> Iterator[None]:
        """The line for an access outside the cycle (a CoE access, the keeper's frame): its
        lock held, and the frames it sends waited for asleep where the cycle's own are
        polled for (from OP on, on the wall clock: `_poll_for_frames`). Such an access has
        milliseconds to spare; a thread polling at real-time priority holds its CPU until
        the answer comes, and the answer may need that CPU: talos_32 over a veth, the
        virtual line's thread out of real time after the configuration's burst
        (`sim_bus.priority`), the keeper polled 2 ms on one core for a frame while the main
        thread's enable sequence held the other, and the line's thread, ready to answer it,
        waited those 2 ms (`perf sched`): the frame was lost, and 40-50 ms went without a
        whole frame, at each start. On a robot the NIC's and the bus's own threads want
        that CPU the same way."""
        with self.lock:
            sockets = self._polled if self._asleep_depth == 0 else ()
            self._asleep_depth += 1
            _poll_for_frames(sockets, poll=False)
            try:
                yield
            finally:
                self._asleep_depth -= 1
                _poll_for_frames(sockets)

    def _keep_windows(self, stop: threading.Event) -> None:
        """DC: SYNC0 wants outputs in every window, also while the cycle is busy elsewhere
        (the cold solve, an enable sequence). Once a period, KEEPER_LEAD before SYNC0 (the
        cycle's own frame goes half a period before it), a frame goes when none went in that
        window (`keep_alive`); a CoE access sends one the same way before it goes, as it
        holds the line for its round trip. A look that comes after its SYNC0 (the keeper
        woke late, or waited for the cycle's frame) sends only when the cycle sent nothing
        for a period: a frame then would land in the next window, which a running cycle's
        frame fills. (Looking at the window of the moment whenever it woke, the keeper sent
        7964 frames beside the cycle's 10325 in 10 s of talos_32, and its frames held the
        line when the cycle's came.)"""
        _above_the_cycle()
        dc = self.dc
        while True:
            _, wake = dc.window(time.monotonic())
            if stop.wait(max(0.0, wake - time.monotonic())):
                return
            start = dc.window(wake)[0]
            if not self._keep_once(stop, (start, start + dc.period_ns * 1e-9)):
                return

    def keep_alive(self, window: tuple[float, float] | None = None) -> None:
        """Real time, while OP: a frame when none went out for KEEP_ALIVE s (DC: since the
        start of `window`, a SYNC0 window's host times (start, SYNC0), by default the one
        open now; past its SYNC0, the one open now when the cycle sent nothing for a
        period), so an acyclic sequence between cycles
        (enabling the drive by CoE) does not starve the slaves' watchdog (DC: their SYNC0
        windows). Drive time needs none (the watchdog is off) and gets none (a frame is a
        cycle of it there)."""
        if not self.clock.runs_alone or not self.operational or self.failure is not None:
            return
        now = time.monotonic()
        if self.dc is not None:
            start, closes = window if window is not None else (self.dc.window(now)[0],
                                                                math.inf)
            if window is not None:
                self.dc.looks += 1
            if now >= closes:
                # a look after its SYNC0 (the keeper woke late, or waited for the line's
                # lock): its window is gone; a running cycle (its own frame within a period)
                # fills the one now open, else the keeper does (a keeper late every time,
                # its interpreter held by a cold solve, fills each window early)
                if now - self._cycle_sent_at < self.dc.period_ns * 1e-9:
                    return
                start = self.dc.window(now)[0]
            if self._sent_at >= start:
                return
            if window is not None:
                self.dc.kept += 1
        elif now - self._last_frame < KEEP_ALIVE:
            return
        # its answer waited for asleep, only when one goes (a DC keeper looks every period)
        with self.acyclic():
            self._frame()

    def _frame(self) -> bool:
        """One process data frame; whether it came back whole. One that did not come back
        in OP is lost, and ridden through (`_rides_through`); past that, or short of its
        working counter, the line fails (sticky, raised)."""
        if self.failure is not None:
            raise self.failure
        wkc = self._send_and_receive()
        if wkc == self._expected_wkc:
            if self._lost_in_a_row:
                log.warning("EtherCAT %s: frames back after %d lost in a row%s", self.interface,
                            self._lost_in_a_row,
                            f" ({self._silence() * 1e3:.0f} ms without one)"
                            if self.clock.runs_alone else "")
                self._lost_in_a_row = 0
            self._whole_at = self._last_frame
            return True
        if wkc < 0 and self.operational and self._rides_through():
            self._lost_in_a_row += 1
            self.lost_frames += 1
            return False
        self.failure = self._diagnose(wkc)
        log.error("%s", self.failure)
        raise self.failure

    def _send_and_receive(self) -> int:
        """One process data frame out and back (the times it went and came kept); its
        working counter, negative when it did not come back."""
        self._sent_at = time.monotonic()
        self.master.send_processdata()
        wkc = self.master.receive_processdata(self.frame_timeout_us)
        self._last_frame = time.monotonic()
        return wkc

    def _silence(self) -> float:
        """s from the last whole frame to the end of the last exchange: what the drives went
        without."""
        return self._last_frame - self._whole_at

    def _drives_hold(self) -> float:
        """s the drives hold their outputs without a frame: their process data watchdog."""
        return self.watchdog if self.watchdog is not None else DEFAULT_WATCHDOG

    def _rides_through(self) -> bool:
        """Whether the frame just lost is ridden through (`LOST_FRAMES_IN_A_ROW`): in real
        time while the drives' watchdog has not passed since the last whole frame, on drive
        time up to LOST_FRAMES_IN_A_ROW in a row."""
        if self.clock.runs_alone:
            return self._silence() < self._drives_hold()
        return self._lost_in_a_row < LOST_FRAMES_IN_A_ROW

    def _fails_at(self) -> str:
        """When frames that stay lost fail the line, in words."""
        if self.clock.runs_alone:
            return (f"{self._silence() * 1e3:.0f} ms without a whole frame; "
                    f"the line fails at the drives' watchdog, {self._drives_hold() * 1e3:g} ms")
        return f"the line fails at {LOST_FRAMES_IN_A_ROW + 1}"

    def _diagnose(self, wkc: int) -> LineLost:
        """The failed frame's report: the slaves in the cycle not in OP (or not answering)
        as read right after it, each with its AL status code in words."""
        in_cycle = [p for p in range(len(self.slaves)) if p not in self._released]
        if wkc < 0:
            # nothing answers, so no state can be read: every slave in the cycle is lost
            silence = (f", {self._silence() * 1e3:.0f} ms without a whole "
                       "frame, past the drives' watchdog"
                       if self.operational and self.clock.runs_alone else "")
            return LineSilent(
                f"EtherCAT {self.interface}: no frame came back within "
                f"{self.frame_timeout_us / 1e3:g} ms (cycle {self.frames}, "
                f"{self._lost_in_a_row + 1} in a row{silence}): "
                f"{', '.join(self.label(p) for p in in_cycle)} lost, the line is broken or "
                "its slaves are off", tuple(in_cycle))
        text = (f"EtherCAT {self.interface}: working counter {wkc}, expected "
                f"{self._expected_wkc} (cycle {self.frames})")
        states = self._read_states(in_cycle)
        lost = [p for p, status in states.items()
                if status is None or status[0] & ec.AL_STATE_MASK != pysoem.OP_STATE]
        return LineLost(text + (": " + "; ".join(self._describe(p, states[p]) for p in lost)
                                   if lost else ""), tuple(lost))

    def release(self, position: int) -> None:
        """Take one slave out of the cycle (to PRE-OP) without failing the others: the
        expected working counter drops by its share. DC, in OP: the slave stays in OP on the
        outputs its transport left (its drive disabled) until the line goes down as a whole
        (`close_line`): a slave that leaves OP is a state change the slaves' host runs for
        it, and the others still on SYNC0 need a frame in every window meanwhile; released
        one by one at the end of a run, the last few of talos_32's slaves dropped out with
        0x001A (working counter 25 of 33) before their turn."""
        if (position in self._released or position in self._leaving
                or not 0 <= position < len(self.slaves)):
            return
        with self.lock:
            if self.dc is not None and self.operational and self.failure is None:
                self._leaving.add(position)
                return
            self._release(position)

    def _release(self, position: int) -> None:
        slave = self.slaves[position]
        if self.operational:
            share = (2 if slave.output else 0) + (1 if slave.input else 0)
            self._expected_wkc -= share
        self._released.add(position)
        slave.state = pysoem.PREOP_STATE
        slave.write_state()

    def close_line(self) -> None:
        """Every slave back to INIT and the interface closed. Best effort. DC, in OP: the
        whole line to SAFE-OP first, in one frame while the keeper still fills the SYNC0
        windows (`_step_down`), so no slave counts a window the stop left empty."""
        if self.master is not None and self.dc is not None and self.operational:
            self._step_down()
        if self._keeper_stop is not None:
            self._keeper_stop.set()
            self._keeper_stop = None
        if self.master is None:
            return
        with self.lock:
            self._close_master()

    def _step_down(self) -> None:
        """DC: every slave of the line from OP to SAFE-OP at once (one broadcast write of AL
        control, as SOEM's ecx_writestate(0)): in SAFE-OP a drive ignores its
        outputs and no longer counts SYNC0 windows, so stopping the frames after is no sync
        error. Best effort: a line that failed or does not answer goes to INIT as it is."""
        with self.lock:
            if self.failure is not None:
                return
            try:
                self.master.state = pysoem.SAFEOP_STATE
                self.master.write_state()
                self.operational = False  # the keeper sends no more
                self._leaving.clear()
            except (pysoem.WkcError, pysoem.NetworkInterfaceNotOpenError):
                pass

    def _close_master(self) -> None:
        try:
            self.master.state = pysoem.INIT_STATE
            self.master.write_state()
        except pysoem.WkcError:
            pass
        finally:
            self.master.close()
            self.master = None
            self._polled = []  # closed with it: the numbers may name other files now
            self.slaves = []
            self.operational = self.mapped = False
            self.dc = None


def _above_the_cycle() -> None:
    """The calling thread (the keeper) one real-time priority above the one that started it,
    when that one runs at a real-time priority: a SOEM master's cyclic thread outranks the
    control loop the same way. At the loop's own priority (SCHED_RR, 100 ms slices) the
    keeper waited for a CPU while the loop's thread computed a cold solve on one core and the
    virtual line (above both) ran on the other: 13 ms without a frame, three SYNC0 windows
    empty, every slave out with 0x001A before the first cycle. Nothing when the loop runs at
    normal priority, or the OS refuses."""
    try:
        policy = os.sched_getscheduler(0)
        if policy in (os.SCHED_RR, os.SCHED_FIFO):
            priority = os.sched_getparam(0).sched_priority + 1
            if priority <= os.sched_get_priority_max(policy):
                os.sched_setscheduler(0, policy, os.sched_param(priority))
    except (OSError, AttributeError):
        pass


def _packet_sockets(interface: str) -> list[int]:
    """This process's raw packet sockets bound to `interface` (SOEM's for this line; another
    line's, or any other file, stay as they are), by file descriptor; none found where there
    is no /proc, and SOEM's sockets are then left as it opened them."""
    try:
        descriptors = sorted(int(fd) for fd in os.listdir("/proc/self/fd"))
    except FileNotFoundError:
        return []
    found = []
    for fd in descriptors:
        try:
            probe = socket.socket(fileno=fd)
        except OSError:  # not a socket, or closed meanwhile (the listing's own among them)
            continue
        try:
            if probe.family == socket.AF_PACKET and probe.getsockname()[0] == interface:
                found.append(fd)
        except OSError:
            pass
        finally:
            probe.detach()  # the descriptor stays open, its owner's
    return found


def _poll_for_frames(descriptors: list[int] | tuple, poll: bool = True) -> None:
    """SOEM's raw sockets non-blocking, so that its wait for a frame polls instead of
    sleeping: SOEM's receive loop calls recv until the frame is in or its timeout passes,
    and on a socket it opened with a 1 us SO_RCVTIMEO the kernel sleeps the thread in recv
    for up to a jiffy, and wakes it when the frame arrives, 40-50 us later on this host than
    a poll sees it. Measured with bare pysoem at SCHED_RR 40 on a virtual line over a veth,
    a frame a millisecond, 3000 frames each, two rounds: the round trip's median 134-139 us
    sleeping against 90-100 us polling with one slave, 172-208 against 157-162 with 32
    (p99 262-598 against 230-233). Only in OP and on the wall clock: the cycle's round
    trip is then short and bounded by the response timeout, while during configuration
    a thread polling for SOEM's 20 ms waits would spend the kernel's real-time bandwidth
    (`sim_bus.priority`). Not `poll`: blocking again, as SOEM opened them, for an access
    outside the cycle (`EthercatMaster.acyclic`)."""
    for fd in descriptors:
        with contextlib.suppress(OSError):  # closed meanwhile: nothing to wait on
            os.set_blocking(fd, not poll)


def _read_state_of(slave) -> tuple[int, int] | None:
    """One slave's (AL status, AL status code) by a read of its own registers (FPRD); None
    when it was not answered."""
    try:
        data = slave._fprd(ec.REG_AL_STATUS, REG_AL_STATUS_SPAN, STATE_READ_TIMEOUT_US)
    except pysoem.WkcError:
        return None
    status = int.from_bytes(data[0:2], "little")
    return (status, int.from_bytes(data[4:6], "little")) if status & ec.AL_STATE_MASK else None


def _why_not_open(interface: str, exc: Exception) -> str:
    """SOEM says only that it could not open the interface: tell a missing interface (looked
    up in this thread's network namespace) from a raw socket refused."""
    try:
        socket.if_nametoindex(interface)
    except OSError:
        return "no such network interface here"
    return f"{exc}; a raw socket needs root or CAP_NET_RAW"


def _errors(error_list: list) -> str:
    return "; ".join(f"slave {getattr(e, 'slave_pos', '?') - 1}: {e}" for e in error_list)
