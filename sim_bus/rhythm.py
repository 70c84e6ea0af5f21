"""The master's rhythm as a virtual device sees it: when its next cycle's first frame is due,
so the thread that answers can look for it awake instead of sleeping until it comes.

Hardware answers a SYNC or an EtherCAT frame within microseconds. A thread asleep on this
kind of host (a virtual machine whose idle CPU halts) wakes 50-150 us after its frame came,
p99 0.3-1.7 ms (a UDP round trip between two processes on two CPUs of the 2-core host:
100-165 us median asleep, 15 us looking), on the master's critical path every cycle. The
look costs the device's CPU up to twice AHEAD a period."""

import itertools
import math
from collections import deque

AHEAD = 150e-6  # s before the next cycle's expected frame from which the thread looks, awake
# s without a frame before one that starts a cycle (a CAN bus's SYNCs of one cycle, or an
# EtherCAT line's cyclic frame and its keeper's or mailbox frames: < 100 us apart)
CYCLE_GAP = 300e-6
RHYTHM = 5  # cycles whose median interval is the expected period


class Rhythm:
    """When the master's next cycle is due, from the times the last cycles' first frames came
    (s on one clock): the median interval between the last RHYTHM + 1 of them after the last.
    A frame within CYCLE_GAP of the one before is of the same cycle (another bus's SYNC).

    A cycle that does not come when due (the master skipped a period: its cycle overran) is
    expected a period later, on the same grid, for RHYTHM periods: a master keeps its grid
    after a late cycle, and a thread that slept until the frame came instead answered the
    cycle after a skipped period 46 us (p90 264 us) after its SYNC, against 22 (27) us for
    any other (talos_arm across processes, 10 s traced), which made one missed cycle likelier
    two. Past RHYTHM periods without one, the master has stopped or changed its rhythm:
    nothing is expected until the next frame."""

    def __init__(self) -> None:
        self._starts: deque[float] = deque(maxlen=RHYTHM + 1)
        self._last_sync = -math.inf
        self._period = math.inf  # s, the median interval
        self._missed = 0  # periods in a row the cycle did not come when due
        self.due = math.inf  # when the next cycle's first frame is expected

    def sync(self, now: float) -> None:
        """A frame that may start a cycle (a SYNC, an EtherCAT frame) came at `now`."""
        if now - self._last_sync > CYCLE_GAP:
            starts = self._starts
            starts.append(now)
            if len(starts) > RHYTHM:
                intervals = sorted(b - a for a, b in itertools.pairwise(starts))
                self._period = intervals[RHYTHM // 2]
                self.due = now + self._period
            self._missed = 0
        self._last_sync = now

    def missed(self) -> None:
        """The cycle did not come when due: expected a period later, RHYTHM times in a row at
        most; then not until the next frame."""
        self._missed += 1
        self.due = self.due + self._period if self._missed <= RHYTHM else math.inf
