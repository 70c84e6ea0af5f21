"""This machine's floor: what the host itself lets a 1 kHz loop keep, so a real-time figure
can be read against it.

Two measurements of the same thing. `bare_loop` is the floor before a run: a cyclic
sleep-and-wake loop with nothing else in it, as a control loop runs. `FloorBeside` is the
floor during a run: on every CPU the run may use, a loop that only sleeps and notes each
wake-up that came more than a period late. It exists because the stalls that cost a run its
cycles are rare and come from outside the guest: on the 2-CPU virtual machine this was built
on, a bare SCHED_FIFO loop on an otherwise idle host lost its CPU for 1-10 ms several times in
30 s and for 47 and 100 ms once each (the host's steal counter advanced over the long ones,
/proc/stat). A 10 s floor taken before ten 10 s starts saw one start's worth of them; the one
beside a start sees that start's own.
"""

import bisect
import math
import os
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass

from driver.clock import REAL_TIME_PRIORITY, CycleClock, WallClock, cpus_awake, prefer_real_time

# SCHED_RR priority of the loops beside a run: above every thread a run of ours starts (the
# master's loop 40, the virtual drives 45, `sim_bus.priority`) and below the kernel's own
# real-time threads (50), so what delays them is the host and the kernel, not the run. They
# only sleep (no spin before the deadline as a control loop does): a wake-up costs some us of
# CPU a period, and only a wake-up more than a period late counts
BESIDE_PRIORITY = 49
PROC_STAT = "/proc/stat"
USER_HZ = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100  # /proc/stat's unit


def bare_loop(duration: float, period: float = 1e-3,
              priority: int = REAL_TIME_PRIORITY) -> CycleClock:
    """The floor before a run: a cyclic sleep-and-wake loop with nothing else in it, for
    `duration` s at `priority` (as a control loop runs; this thread only, given back after);
    with the CPUs kept awake (`cpus_awake`) as the loops it is the floor of keep them. The
    clock holds the missed cycles and the jitter."""
    refused = prefer_real_time(priority) if priority else None
    try:
        clock = CycleClock(period, WallClock())
        with cpus_awake():
            for _ in range(int(round(duration / period))):
                clock.wait()
                clock.check_overrun()
        return clock
    finally:
        if priority and refused is None:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


@dataclass(frozen=True)
class Stall:
    """A wake-up more than a period late on `cpu`: its deadline and when it came (s, the
    monotonic clock, `time.perf_counter`, the clock a real-time loop runs on)."""
    cpu: int
    deadline: float
    woke: float


def host_steal_s() -> dict[int, float]:
    """Per CPU, the time (s) the hypervisor has run something else while this guest's CPU
    wanted to run (/proc/stat's steal column), since boot; empty where there is no such
    file. Its unit is a clock tick (10 ms), so a short stall may not show."""
    try:
        with open(PROC_STAT, encoding="ascii") as stat:
            lines = stat.read().splitlines()
    except OSError:
        return {}
    steal = {}
    for line in lines:
        name, _, rest = line.partition(" ")
        if name.startswith("cpu") and name[3:].isdigit():
            fields = rest.split()
            if len(fields) >= 8:
                steal[int(name[3:])] = int(fields[7]) / USER_HZ
    return steal


class FloorBeside:
    """The floor during a run (`with FloorBeside(cpus) as floor: ...`): one loop per CPU of
    `cpus`, each pinned there at `priority`, noting every stall until the block ends. Read
    afterwards with `figures`."""

    def __init__(self, cpus: Iterable[int], period: float = 1e-3,
                 priority: int = BESIDE_PRIORITY):
        self.cpus = sorted(cpus)
        self.period = period
        self.priority = priority
        self.stalls: list[Stall] = []  # appended by the loops, read after they end
        self.refused: str | None = None  # why real-time priority was refused (once)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._steal_before: dict[int, float] = {}
        self.steal_s: dict[int, float] = {}

    def __enter__(self) -> "FloorBeside":
        self._steal_before = host_steal_s()
        for cpu in self.cpus:
            thread = threading.Thread(target=self._watch, args=(cpu,), daemon=True,
                                      name=f"floor-beside-{cpu}")
            thread.start()
            self._threads.append(thread)
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join()
        after = host_steal_s()
        self.steal_s = {cpu: round(after[cpu] - self._steal_before.get(cpu, 0.0), 3)
                        for cpu in self.cpus if cpu in after}

    def _watch(self, cpu: int) -> None:
        # sched_setaffinity and sched_setscheduler with pid 0 act on the calling thread
        os.sched_setaffinity(0, {cpu})
        refused = prefer_real_time(self.priority)
        if refused is not None:
            self.refused = refused
        period, stop, stalls = self.period, self._stop, self.stalls
        clock = time.perf_counter
        deadline = clock()
        while not stop.is_set():
            deadline += period
            remaining = deadline - clock()
            if remaining > 0:
                time.sleep(remaining)
            woke = clock()
            if woke > deadline + period:
                stalls.append(Stall(cpu, deadline, woke))
                deadline += math.floor((woke - deadline) / period) * period

    def in_stalls(self, missed_at: Iterable[tuple[float, int]]) -> int:
        """Of a run's missed cycles (`missed_at`: when, s on the monotonic clock, and how
        many, as `controller.loop.LoopReport` keeps them), those a stall beside it explains:
        a stall of any CPU within the cycles behind the moment they were found missed (one
        period more, the cycle that overran or slept through them)."""
        stalls = sorted((s.deadline, s.woke) for s in self.stalls)
        starts = [start for start, _ in stalls]
        explained = 0
        for at, cycles in missed_at:
            since = at - (cycles + 1) * self.period
            # the stalls that began before `at`; any of them that ended after `since` overlaps
            last = bisect.bisect_right(starts, at)
            if any(woke > since for _, woke in stalls[:last]):
                explained += cycles
        return explained

    def longest_stall(self, begin: float, end: float) -> dict | None:
        """The longest stall of any CPU that overlapped `begin`..`end` (s, the monotonic
        clock): its CPU, its length and how long before `end` it ended (ms); None when there
        was none. Read over the moments before a run failed, it says whether the host had
        just taken a CPU away: a line on distributed clocks is out of sync after a few empty
        SYNC0 windows (3 in a row at 1 kHz with the sync error limit of 9 talos_32's drives
        have, 0x10F1:02), which a 3-4 ms stall of the master's CPU leaves."""
        overlapping = self._between(begin, end)
        if not overlapping:
            return None
        stall = max(overlapping, key=lambda s: s.woke - s.deadline)
        return {"cpu": stall.cpu, "ms": round((stall.woke - stall.deadline) * 1e3, 2),
                "ended_ms_before": round(max(end - stall.woke, 0.0) * 1e3, 2)}

    def _between(self, begin: float, end: float) -> list[Stall]:
        """The stalls that overlapped `begin`..`end`."""
        return [s for s in self.stalls if s.woke > begin and s.deadline < end]

    def figures(self, begin: float = -math.inf, end: float = math.inf) -> dict:
        """The floor between `begin` and `end` (s, the monotonic clock: a run's cycles):
        the deadlines missed on any of the CPUs (a stall of either costs a cycle whose
        master and drives share them; stalls that overlap count once), their share of the
        span's periods, the longest stall (ms), and the host's steal per CPU over the whole
        block (s)."""
        spans = sorted((max(s.deadline, begin), min(s.woke, end))
                       for s in self._between(begin, end))
        missed, longest, merged_end = 0, 0.0, -math.inf
        merged_start = -math.inf
        for start, stop in [*spans, (math.inf, math.inf)]:
            if start > merged_end:  # a span of its own: count the last one
                if merged_end > merged_start:
                    # (a span cut at the run's end may come a few ulp short of whole periods)
                    missed += int((merged_end - merged_start) / self.period + 1e-6)
                    longest = max(longest, merged_end - merged_start)
                merged_start, merged_end = start, stop
            else:
                merged_end = max(merged_end, stop)
        periods = (end - begin) / self.period if math.isfinite(end - begin) else math.nan
        return {"cpus": self.cpus, "missed": missed,
                "missed_percent": round(100 * missed / periods, 3) if periods > 0 else None,
                "longest_stall_ms": round(longest * 1e3, 2),
                "host_steal_s": self.steal_s,
                **({"priority_refused": self.refused} if self.refused else {})}
