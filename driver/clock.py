"""The time a loop is given, and its cycle clock: when to trigger the next SYNC.

Two clocks answer the same two questions, what time it is and "wake me at this deadline": the
wall clock (real time: sleeping to a deadline sleeps, and a host that wakes the loop late is
seen) and drive time (lock-step with virtual drives: time passes only as the drives cycle, so
"sleeping" to a deadline is drive time reaching it, at once, on every run alike). What runs on
a clock has one code path whichever it is given; `clock_for` is where the choice is made."""

import contextlib
import gc
import heapq
import logging
import math
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np

# SCHED_RR priority of a real-time control process: above every normal process (a busy host's
# CPU-bound work no longer delays a cycle), below the kernel's own real-time threads (50)
REAL_TIME_PRIORITY = 40
SPIN_BEFORE_DEADLINE = 200e-6  # s: sleep until this close to the deadline, then spin
STATS_WINDOW = 200_000  # values kept for percentiles (3 min at 1 kHz)


def prefer_real_time(priority: int = REAL_TIME_PRIORITY) -> str | None:
    """Ask for round-robin real-time scheduling for this process (the threads it starts
    afterwards inherit it), as a control loop on a robot runs. Call before starting threads
    that must keep up with the loop, in real time only: a lock-step run has no deadline and
    would only take the CPU from everyone else. Returns None, or why it was refused (not
    root and no CAP_SYS_NICE, or no such scheduler here); the loop then runs at normal
    priority. The kernel keeps 5 % of each second for other work (sched_rt_runtime_us), so an
    overrunning loop cannot lock a machine up."""
    try:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        return str(getattr(exc, "strerror", None) or exc)
    return None


MCL_CURRENT = 1  # <sys/mman.h>


def lock_memory() -> str | None:
    """Keep the pages this process has mapped so far in RAM (mlockall MCL_CURRENT), so no
    cycle waits for one of them to come back from swap: called with the real-time priority,
    once the controller is built. Not MCL_FUTURE, as real-time C programs often add: with it
    every later mapping (an 8 MiB thread stack, a buffer of numba's or Zenoh's) is populated
    whole inside the call that maps it, holding the interpreter's lock, and the EtherCAT
    line's keeper could not send a frame: talos_32 over a veth lost the line's watchdog
    before its first cycle in 3 starts of 3 with it, and started 2 of 2 without it. Returns
    None, or why it was refused (the loop runs on without it)."""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    if libc.mlockall(MCL_CURRENT) != 0:
        return os.strerror(ctypes.get_errno())
    return None


CPU_DMA_LATENCY = "/dev/cpu_dma_latency"  # the kernel's PM QoS request for CPU wake-up latency
_NO_LATENCY = (0).to_bytes(4, sys.byteorder)  # a native s32: 0 us


@contextlib.contextmanager
def cpus_awake() -> Iterator[str | None]:
    """While inside, ask the kernel for a CPU wake-up latency of 0 (PM QoS,
    /dev/cpu_dma_latency, held while its descriptor is open), so an idle CPU polls instead
    of entering a sleep state: a thread woken there (by its deadline, or by the frame it
    waits for) first waits for its CPU to wake. Real-time Linux practice (cyclictest holds the
    same request by default). Measured on this 2-core virtual machine, whose idle CPUs halt to
    the host: with it, talos_32 over the veth missed 0.38-1.43 % of its cycles and one joint
    across processes 0.12-1.54 %, in the minutes before without it 1.35-3.67 % and 1.61-6.59 %
    (bus-bench --robot, 3 starts each). Yields None, or why the request was refused (not root:
    the device is root's alone; the loop runs on)."""
    try:
        fd = os.open(CPU_DMA_LATENCY, os.O_WRONLY)
        try:
            os.write(fd, _NO_LATENCY)
        except OSError:
            os.close(fd)
            raise
    except OSError as exc:
        yield str(exc.strerror or exc)
        return
    try:
        yield None
    finally:
        os.close(fd)


_HELD = contextlib.ExitStack()  # requests held for the process's life (the kernel ends them)


def keep_cpus_awake() -> str | None:
    """`cpus_awake` for the rest of this process's life (a real-time loop's or the virtual
    drives' process): None, or why it was refused."""
    return _HELD.enter_context(cpus_awake())


@contextlib.contextmanager
def collector_off_the_cycle() -> Iterator[None]:
    """Keep Python's cyclic garbage collector from stopping a running loop for tens of ms.

    By the time a loop starts, the process holds a few hundred thousand long-lived objects
    (numba, Zenoh, canopen, numpy); a full collection walks them all: 38-57 ms here, measured
    at start-up with `gc.callbacks` (none came during a 120 s run, but one comes whenever
    enough of what a loop makes survives, and it would cost 40-odd cycles at once). The
    collector stays on for what the loop makes and drops; what exists at the start is
    collected once and frozen (`gc.freeze`, documented for exactly this), and unfrozen at the
    end, so a process that runs several loops (a test session) gets it back."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


class RingStats:
    """Percentiles over the last `window` values, max and count over all of them, with no
    allocation per value."""

    def __init__(self, window: int = STATS_WINDOW):
        self._values = np.zeros(window)
        self._window = window
        self.count = 0
        self.max = 0.0

    def add(self, value: float) -> None:
        count = self.count
        self._values[count % self._window] = value
        self.count = count + 1
        if value > self.max:  # NaN never is: as max() kept the maximum
            self.max = value

    def percentile(self, q: float) -> float:
        n = min(self.count, len(self._values))
        return float(np.percentile(self._values[:n], q)) if n else math.nan

    def recent_percentiles(self, qs: tuple[float, ...], last: int) -> list[float]:
        """Percentiles `qs` of the last `last` values only (at most the window). What a
        running loop reports every second: one partial sort of that second's values, where
        one over the whole window took 1.5 ms per percentile at 200 000 values, a missed
        cycle every second of a long real-time run."""
        size = len(self._values)
        n = min(last, self.count, size)
        if n <= 0:
            return [math.nan] * len(qs)
        end = self.count % size
        values = (self._values[end - n:end] if n <= end else
                  np.concatenate((self._values[size - (n - end):], self._values[:end])))
        return np.percentile(values, qs).tolist()

    def recent(self) -> np.ndarray:
        """The values kept (the last `window`), oldest first."""
        n = min(self.count, len(self._values))
        start = self.count % len(self._values) if self.count > len(self._values) else 0
        return np.roll(self._values[:n], -start)


# s: two times on a clock closer than this are the same time. Drive time is a sum of periods,
# each addition rounded, so a deadline that falls exactly on a cycle can come out a few ulp
# either side of it; a watchdog compares with this margin to judge it on that cycle every run.
SAME_TIME = 1e-9


class WallClock:
    """Real time: the monotonic wall clock (s, `time.perf_counter`). It runs alone: time
    passes between cycles, so a watchdog must also be looked at while no cycle runs."""

    now = staticmethod(time.perf_counter)
    # time passes between cycles: the watchdogs that time a peer on the wall (an ESC's
    # process data watchdog, a keeper that sends frames while the cycle is busy) are on
    runs_alone = True
    # s a master waits for a drive's answer (a cycle's samples, a frame back): a sample
    # 100 ms late is a dead drive, the drives' own default process data watchdog
    response_timeout = 0.1
    # s a watchdog on received frames waits past its timeout for a receive path that has not
    # yet handled a frame received after the deadline (`driver.canopen_health.Health.check`):
    # a receive thread held up with the rest of the process (a stall of the host) resumes
    # with the frames queued meanwhile, and a watchdog thread that resumes before it would
    # judge a silence that is only in its queue. Time to catch up, far below a heartbeat
    receive_grace = 0.02

    @staticmethod
    def advance(seconds: float) -> None:
        """The drives cycled: wall time passed on its own."""

    @staticmethod
    def span(seconds: float, period: float) -> str:
        """A time span as a report says it on this clock."""
        return f"{seconds * 1e3:.0f} ms"

    @staticmethod
    def sleep_until(deadline: float) -> None:
        """Sleep to `deadline` (s on this clock): sleep until SPIN_BEFORE_DEADLINE before it,
        then spin (a sleep wakes up to ~100 us late; the spin makes the wake-up exact)."""
        remaining = deadline - time.perf_counter()
        if remaining > SPIN_BEFORE_DEADLINE:
            time.sleep(remaining - SPIN_BEFORE_DEADLINE)
        while time.perf_counter() < deadline:
            pass

    @staticmethod
    def for_bus() -> "WallClock":
        """The clock of one bus or line of a run on this clock: the wall clock, which all
        share."""
        return WallClock()

    @staticmethod
    def timers() -> "WallTimers":
        """The own time of a party on this clock (a virtual drive): the wall clock."""
        return WallTimers()


class DriveClock:
    """Lock-step: drive time (s), which passes only as the drives cycle: the bus that sends a
    SYNC advances it by a period (`advance`), whoever runs the cycle (the loop, or a test
    calling `sync` itself). Waiting for a deadline is the drives cycling up to it, so it
    returns at once with the clock there: a lock-step loop is never late and runs as fast as
    the drives answer. Nothing happens between cycles, so no watchdog needs a thread."""

    runs_alone = False
    # s a master waits for a drive's answer: on drive time a late answer is no failure (the
    # drive is computed on the same, perhaps busy, host), only none is
    response_timeout = 1.0
    # on drive time the frames of a cycle are handled before the cycle's watchdogs look:
    # no receive path to wait for
    receive_grace = 0.0

    def __init__(self) -> None:
        self._now = 0.0

    def now(self) -> float:
        return self._now

    def advance(self, seconds: float) -> None:
        """The drives cycled: `seconds` of drive time passed."""
        self._now += seconds

    @staticmethod
    def span(seconds: float, period: float) -> str:
        """A time span as a report says it on this clock: in cycles, then drive seconds."""
        return f"{round(seconds / period)} cycles ({seconds:.3f} s of drive time)"

    def sleep_until(self, deadline: float) -> None:
        self._now = max(self._now, deadline)

    @staticmethod
    def for_bus() -> "DriveClock":
        """The clock of one bus or line of a run on this clock: a drive time of its own,
        which that bus's SYNCs (or that line's frames) advance, so a robot of four buses does
        not advance one clock four periods a cycle."""
        return DriveClock()

    @staticmethod
    def timers() -> "DriveTimers":
        """The own time of a party on this clock (a virtual drive): its cycles, which
        `DriveTimers.tick` counts."""
        return DriveTimers()


Job = Callable[[float], None]  # a periodic job, given the time it runs at (s)


class WallTimers:
    """A party's own time in real time (a virtual drive's, as a real drive keeps its own
    clock whatever its master does): the monotonic wall clock, whose periodic jobs run in the
    process's one timer thread (`_WallJobs`), whether or not any cycle comes."""

    now = staticmethod(time.monotonic)

    def tick(self, period: float) -> None:
        """A cycle of the party's (a SYNC it took): the wall clock moves by itself."""

    @staticmethod
    def every(interval: float, job: Job) -> Callable[[], None]:
        """Run `job(now)` every `interval` s from one to two intervals from now on (on the
        interval's grid of the monotonic clock), until the returned stop is called."""
        return _WALL_JOBS.every(interval, job)

    @staticmethod
    def later(delay: float, job: Callable[[], None]) -> None:
        """Run `job()` once, `delay` s from now, in a thread of its own: what a device does
        in its own time after a request (a reset's boot-up), so the requester, which turns to
        waiting for the answer after its send returns, is not outrun by it."""
        timer = threading.Timer(delay, job)
        timer.daemon = True
        timer.start()


class _WallJobs:
    """Every periodic job of a process's parties on the wall clock, in one daemon thread,
    each on the grid of its interval: a process of seven virtual drives had fourteen threads
    (a master watch every 10 ms and a heartbeat each), 770 wake-ups a second, each a thread
    switch on the CPU that answers the master's frames; on a common grid the watches of all
    drives run in one wake-up, 100 a second. A job that raises is logged and dropped (its
    thread of its own died with it), the others run on. The thread starts with the first
    job, from the thread that asks: a real-time drive's thread makes it real-time too."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._jobs: list[list] = []  # heap of [due (s), order, interval (s), job or None]
        self._order = 0
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None

    def every(self, interval: float, job: Job) -> Callable[[], None]:
        now = time.monotonic()
        due = (math.floor(now / interval) + 2) * interval
        with self._lock:
            self._order += 1
            entry = [due, self._order, interval, job]
            heapq.heappush(self._jobs, entry)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, daemon=True,
                                                name="wall-timers")
                self._thread.start()
            elif self._jobs[0] is entry:
                self._wake.set()  # sooner than the thread sleeps to

        def stop() -> None:
            entry[3] = None  # the thread drops it when it comes due

        return stop

    def _run(self) -> None:
        jobs, lock, wake = self._jobs, self._lock, self._wake
        while True:
            with lock:
                due = jobs[0][0] if jobs else math.inf
            now = time.monotonic()
            if due > now:
                wake.wait(None if due == math.inf else due - now)
                wake.clear()
                continue
            ran = []
            with lock:
                while jobs and jobs[0][0] <= now:
                    entry = heapq.heappop(jobs)
                    if entry[3] is not None:
                        ran.append(entry)
            for entry in ran:
                job = entry[3]
                if job is None:  # stopped meanwhile
                    continue
                try:
                    job(now)
                except Exception:
                    logging.getLogger(__name__).exception("a timed job failed; dropped")
                    continue
                # the next grid point after now: a stalled host's missed runs are not caught up
                entry[0] = (math.floor(now / entry[2]) + 1) * entry[2]
                with lock:
                    heapq.heappush(jobs, entry)


_WALL_JOBS = _WallJobs()


class DriveTimers:
    """A party's own time in lock-step (a virtual drive's): the cycles it took, `tick`ed one
    period each (integer ns: a beat every 100 ms falls on every 100th cycle of 1 ms, never on
    the 101st by a rounding of float sums). A periodic job runs inside the `tick` that
    reaches its time, in the thread that ticks, so it falls on the same cycle in every run;
    between ticks nothing runs and no time passes, however long the host stalls."""

    def __init__(self) -> None:
        self._ns = 0
        self._period, self._step = 0.0, 0  # the last tick's period (s) and its ns
        self._jobs: list[list] = []  # [due ns, interval ns, job or None once stopped]
        self._next_due = math.inf
        self._lock = threading.Lock()

    def now(self) -> float:
        return self._ns * 1e-9

    def tick(self, period: float) -> None:
        """One cycle of `period` s passed; the jobs due by now run (each once)."""
        if period != self._period:  # the same every cycle: rounded once
            self._period, self._step = period, round(period * 1e9)
        self._ns += self._step
        if self._ns >= self._next_due:
            self._run_due()

    def every(self, interval: float, job: Job) -> Callable[[], None]:
        """Run `job(now)` at each tick that reaches another `interval` s from now on, until
        the returned stop is called."""
        step = max(1, round(interval * 1e9))
        entry = [self._ns + step, step, job]
        with self._lock:
            self._jobs.append(entry)
            self._next_due = min(self._next_due, entry[0])

        def stop() -> None:
            with self._lock:
                entry[2] = None
                if entry in self._jobs:
                    self._jobs.remove(entry)
                self._next_due = min((e[0] for e in self._jobs), default=math.inf)

        return stop

    @staticmethod
    def later(delay: float, job: Callable[[], None]) -> None:
        """Run `job()` now: no drive time passes between two cycles, and a lock-step
        requester (a master resetting the drive) waits for the answer before it cycles
        again, so what the device does in its own time after a request is done before
        anyone can look."""
        job()

    def _run_due(self) -> None:
        now = self._ns
        with self._lock:
            due = [entry for entry in self._jobs if entry[0] <= now]
            for entry in due:
                while entry[0] <= now:  # a job shorter than the cycle runs once a cycle
                    entry[0] += entry[1]
            self._next_due = min((e[0] for e in self._jobs), default=math.inf)
        for entry in due:
            job = entry[2]
            if job is not None:
                job(now * 1e-9)


Clock = WallClock | DriveClock


def clock_for(lockstep: bool) -> Clock:
    """The clock of a run: drive time in lock-step (virtual drives), else the wall clock."""
    return DriveClock() if lockstep else WallClock()


class CycleClock:
    """The loop's rhythm on the clock it is given: a deadline each period, the deadlines a
    late cycle skipped counted as missed, the wake-ups' lateness and period jitter."""

    def __init__(self, period: float, clock: WallClock | DriveClock):
        self.period = period
        self.clock = clock
        self.missed_cycles = 0
        self.jitter_us = RingStats()  # |actual - nominal period| between wake-ups
        self.restart()

    def restart(self) -> None:
        """Deadlines count from now (after a long first cycle, say)."""
        self._deadline = self.clock.now()
        self._last_wake: float | None = None
        self.wake_lateness = 0.0

    def wait(self, trim: float = 0.0) -> int:
        """Return at the next deadline; a deadline already more than a period past is skipped
        and counted as missed. Returns the deadlines this call skipped (what came before it,
        the previous cycle or the host, overran); `wake_lateness` is how late this wake-up
        came after its deadline (s). `trim` (s) moves this deadline: an EtherCAT line on
        distributed clocks keeps the cycle on its reference clock."""
        clock, period = self.clock, self.period
        self._deadline += period + trim
        now = clock.now()
        late = 0
        if now > self._deadline + period:
            late = int((now - self._deadline) / period)
            self.missed_cycles += late
            self._deadline += late * period
        clock.sleep_until(self._deadline)
        wake = clock.now()
        self.wake_lateness = wake - self._deadline
        if self._last_wake is not None:
            self.jitter_us.add(abs(wake - self._last_wake - period) * 1e6)
        self._last_wake = wake
        return late

    def miss(self) -> None:
        """This cycle woke in time but could not run (its sample never came): missed."""
        self.missed_cycles += 1

    def check_overrun(self) -> bool:
        """Call when the cycle's work is done: counts it as missed if it overran its period."""
        if self.clock.now() > self._deadline + self.period:
            self.missed_cycles += 1
            return True
        return False
