"""The master's side of distributed clocks on one EtherCAT line (`driver.ethercat_master` in DC
mode): what SOEM's examples do around `ec_configdc`, in one place.

Start-up, with the slaves in SAFE-OP: `config_dc` measures the propagation delays and writes
every slave's offset and delay (pysoem's `config_dc`, i.e. SOEM's ecx_configdc; the linked
line does the same register writes), the delays are read back (0x0928) to be reported, and
SYNC0 is activated on every slave with the line's period and SYNC0_SHIFT of it
(`dc_sync`: the first SYNC0 100 ms later, SOEM's SyncDelay).

Every cycle: the frame carries the reference clock's system time (SOEM adds an FRMW on 0x0910
to the process data frame, which also feeds every other slave's time control loop: the drift
compensation), `dc_time` after the exchange. `observe` takes the master's offset from the
reference clock's cycle, the phase at which its frame passed the reference clock, and a PI on
it moves the master's next wake-up (`take_trim`), as SOEM's ec_sync does in its examples (the
first frame's offset is taken whole, so the master starts in phase, and so is an offset that
stays large for several frames, after the loop's clock restarted or slipped): the
master's cycle follows the reference clock instead of its own crystal, so the frames keep
their place before SYNC0 however the two clocks drift.
"""

import struct
from collections import deque

from driver.clock import RingStats
from driver.interface import DriveError

SYNC0_SHIFT = 0.5  # share of the period from the frame's phase to SYNC0: the outputs' window
MASTER_PHASE = 0.0  # the master's frame at this share of the reference clock's cycle
# the PI of SOEM's ec_sync example: a hundredth of the offset, plus an integral of its sign
PROPORTIONAL = 0.01
INTEGRAL_STEP = 0.05  # ns of trim per cycle the offset kept its sign
# the keeper looks for a frame in the window this share of the period before its SYNC0: late
# enough that a running cycle's frame (at MASTER_PHASE, a late wake-up included) went before,
# early enough that its own frame still lands in the window when the cycle's did not, after
# waiting for the interpreter (the switch interval, KEEPER_SWITCH_SHARE of the period)
KEEPER_LEAD = 0.3
# a phase error this share of the period or more in RELOCK_FRAMES frames in a row, one way, is
# stepped out at once (by the smallest of them: a frame the host sent late only adds to its
# wake-up's error); the PI alone moves 1 % a cycle, hundreds of cycles from a phase slip
RELOCK_SHARE = 0.1
RELOCK_FRAMES = 8
SETTLE_TIME = 2.0  # s: offsets count for the figures from then on
REG_SYSTEM_TIME_DELAY = 0x0928
_U32 = struct.Struct("<I")


class DcLine:
    """DC of one line: its delays, its SYNC0 and the master's offset from the reference."""

    def __init__(self, name: str, period: float, shift: float | None = None):
        self.name = name
        self.period_ns = int(round(period * 1e9))
        self.shift_ns = int(round((SYNC0_SHIFT * period if shift is None else shift) * 1e9))
        self.delays_ns: list[int] = []
        self.offsets_ns = RingStats()  # |offset| after settling
        self.cycles = 0
        self.last_offset_ns = 0
        self._integral = 0
        self._trim = 0.0
        self._anchor: tuple[float, int] | None = None  # (host time, reference time) of a frame
        self._recent: deque[int] = deque(maxlen=RELOCK_FRAMES)  # the last frames' offsets, ns
        self.elapsed_periods = 1  # SYNC0 periods between the last two cycles' frames
        self.kept = 0  # frames the keeper sent into windows the cycle left empty
        self.waits_us = RingStats()  # the cycle's wait for the line's lock
        self.round_trips_us = RingStats()  # the cycle's frame, sent to answered
        self.looks = 0  # the keeper's looks

    def configure(self, master, slaves) -> None:
        """Delays and offsets measured and written, SYNC0 activated on every slave."""
        try:
            found = master.config_dc()
        except Exception as exc:  # pysoem raises its own kinds for a failed register access
            raise DriveError(f"EtherCAT {self.name}: distributed clocks set-up failed: "
                             f"{exc!r}") from None
        if not found:
            raise DriveError(f"EtherCAT {self.name}: no slave has distributed clocks, the "
                             "line cannot run in DC mode (use sync = \"free_run\")")
        # what config_dc wrote, read back (pysoem's register read; it keeps SOEM's pdelay
        # to itself)
        self.delays_ns = [_U32.unpack(slave._fprd(REG_SYSTEM_TIME_DELAY, 4))[0]
                          for slave in slaves]
        for slave in slaves:
            slave.dc_sync(True, self.period_ns, self.shift_ns)

    def describe(self) -> str:
        """One line for the start-up report."""
        return (f"{self.name}: distributed clocks, SYNC0 every {self.period_ns / 1e3:g} us "
                f"shifted {self.shift_ns / 1e3:g} us, reference clock slave 0, propagation "
                f"delays (ns) " + " ".join(str(d) for d in self.delays_ns))

    def observe(self, dc_time: int, sent_at: float) -> None:
        """The reference clock's time as the cycle's frame read it (`sent_at`: the host's
        monotonic time it went out): the master's offset from its place in the cycle, and the
        trim of the next wake-up."""
        period = self.period_ns
        if self._anchor is not None:
            self.elapsed_periods = max(1, -(-(dc_time - self._anchor[1]) // period))
        self._anchor = (sent_at, dc_time)
        offset = (dc_time - int(MASTER_PHASE * period)) % period
        if offset > period // 2:
            offset -= period
        self.last_offset_ns = offset
        self.cycles += 1
        if self.cycles == 1:  # the first frame: straight to the phase, then follow it
            self._trim = -offset * 1e-9
            return
        recent = self._recent
        recent.append(offset)
        if len(recent) == RELOCK_FRAMES and (
                min(recent) >= RELOCK_SHARE * period or max(recent) <= -RELOCK_SHARE * period):
            # off the phase for good (the loop restarted its clock after the cold solve, or
            # slipped): back to it at once, then follow it
            self._trim = -min(recent, key=abs) * 1e-9
            self._integral = 0
            recent.clear()
            return
        self._integral += (offset > 0) - (offset < 0)
        self._trim = -(offset * PROPORTIONAL + self._integral * INTEGRAL_STEP) * 1e-9
        if self.cycles * period > SETTLE_TIME * 1e9:
            self.offsets_ns.add(abs(offset))

    def exchanged(self, waited: float, round_trip: float) -> None:
        """A cycle's exchange (s): how long it waited for the line, its frame's round trip."""
        self.waits_us.add(waited * 1e6)
        self.round_trips_us.add(round_trip * 1e6)

    def window(self, now: float) -> tuple[float, float]:
        """Host times (monotonic) of the last SYNC0 before `now` (the start of the window the
        next SYNC0 takes its outputs from) and of the next keeper's look (KEEPER_LEAD before
        a SYNC0) after `now`."""
        sent_at, dc_time = self._anchor
        period = self.period_ns
        reference = dc_time + int((now - sent_at) * 1e9)  # drift: ppm over a few periods
        since_sync0 = (reference - self.shift_ns) % period
        look = self.shift_ns - int(KEEPER_LEAD * period)
        to_keeper = (look - reference) % period or period
        return now - since_sync0 * 1e-9, now + to_keeper * 1e-9

    def next_frame(self, now: float) -> tuple[float, float]:
        """Host times (monotonic) of the master's next frame phase (MASTER_PHASE of the
        reference clock's cycle) at or after `now`, and of the SYNC0 that takes the outputs
        of a frame sent then: where a frame outside the cycle goes (`EthercatMaster.
        pass_image`), so it lands where the cycle's would, early in a window, not at
        whatever phase the caller came by."""
        sent_at, dc_time = self._anchor
        period = self.period_ns
        reference = dc_time + int((now - sent_at) * 1e9)
        to_phase = (int(MASTER_PHASE * period) - reference) % period
        to_sync0 = (self.shift_ns - reference - to_phase) % period or period
        return now + to_phase * 1e-9, now + (to_phase + to_sync0) * 1e-9

    def take_trim(self) -> float:
        """s to add to the next period of the master's clock (then 0 until the next frame)."""
        trim, self._trim = self._trim, 0.0
        return trim

    def summary(self) -> str:
        text = (self._offsets() + f"; the keeper filled {self.kept} of {self.looks} windows "
                "it looked at")
        if self.round_trips_us.count:
            waits, trips = self.waits_us, self.round_trips_us
            text += (f"; the cycle's frame waited for the line {waits.percentile(50):.0f} us "
                     f"median (p99 {waits.percentile(99):.0f}), its round trip "
                     f"{trips.percentile(50):.0f} us median (p99 {trips.percentile(99):.0f})")
        return text

    def _offsets(self) -> str:
        if not self.offsets_ns.count:
            return (f"{self.name}: master-to-reference-clock offset not settled yet "
                    f"({self.cycles} cycles, last {self.last_offset_ns / 1e3:.1f} us)")
        return (f"{self.name}: master-to-reference-clock offset after settling "
                f"({self.offsets_ns.count} cycles): median "
                f"{self.offsets_ns.percentile(50) / 1e3:.1f} us, p99 "
                f"{self.offsets_ns.percentile(99) / 1e3:.1f} us, max "
                f"{self.offsets_ns.max / 1e3:.1f} us")
