"""Real-time scheduling for a process of virtual drives, which stand in for hardware: a real
drive answers a SYNC or a frame within microseconds whatever the master's host is doing, so
the process that plays it must not wait behind CPU-bound work (another master starting up,
a compilation, a test's load), or the harness, not the master, is what a run measures."""

import os
import threading
import time
from collections import deque
from collections.abc import Callable

# SCHED_RR priority of a virtual drives' process: above every normal process and above the
# master's loop (driver.clock.REAL_TIME_PRIORITY, 40), below the kernel's own real-time
# threads (50). A drive is other hardware: it never waits for the master's host. Below the
# master (it was 10) the master's real-time threads (loop, receive thread, Zenoh's workers,
# all at 40) took both cores of a 2-core host, and the drive's heartbeat thread went unrun
# for over 200 ms: the master declared a healthy drive lost ("heartbeat missing for 219 ms")
# in 2 runs of 6 on a loaded host. It blocks on its bus between frames, so it takes no more
# CPU than the frames need
HARDWARE_PRIORITY = 45


def answer_like_hardware(priority: int = HARDWARE_PRIORITY) -> str | None:
    """Every thread of this process (those already running too: the bus's receive thread
    starts with the bus) and those it starts later at SCHED_RR `priority`. Call once the
    drives are ready, not before: start-up is heavy (imports, compiled code), and ten
    processes starting at real-time priority starve everything else. Returns None, or why it
    was refused (the drives still work, answering later on a busy host)."""
    param = os.sched_param(priority)
    try:
        for tid in os.listdir("/proc/self/task"):
            try:
                os.sched_setscheduler(int(tid), os.SCHED_RR, param)
            except ProcessLookupError:
                pass  # a thread that ended meanwhile
    except (OSError, AttributeError) as exc:
        return str(getattr(exc, "strerror", None) or exc)
    return None


# The kernel lets real-time threads run sched_rt_runtime_us of every sched_rt_period_us (by
# default 950 ms a second) and then stops every one of them on that CPU until the period ends.
# A virtual line's thread is CPU-bound while a master configures it (SOEM sends its next
# mailbox frame as soon as the last one is answered: talos_32's 32 slaves kept it busy for
# 2 s), so it hit that limit and stopped for up to 50 ms at the period's end, every time at
# the same phase of the second; SOEM's 20 ms wait for a frame ran out, one PDO entry read as
# 0 bits, and 1 start in 5 failed with a process image the master refused (measured: 24
# starts of talos_32 over a veth, each master SIGKILLed 3 s after enabling). A hardware ESC
# answers in microseconds whatever its host does, so the thread keeps its CPU time over the
# last second (as the kernel counts: a thread that cycles at 80 % is never stopped) below
# BUDGET_HIGH, taking normal priority while it has used more: looked at every BUDGET_WINDOW,
# it cannot pass the kernel's 95 % before the next look. (Judged on 100 ms windows alone, a
# thread above 80 % for one of them left real time, which a thread that cycles near that
# must not: talos_arm's CAN drives with it missed 0.3-42 % of cycles in 10 starts, the set
# before without it 0.6-2.2 %, on a host that was slowing down.)
BUDGET_WINDOW = 0.02  # s of wall time: how often the thread's CPU time is looked at
BUDGET_WINDOWS = 50  # windows in the second the kernel counts a real-time thread's time over
BUDGET_HIGH = 0.9  # share of the last second above which the thread leaves real time
BUDGET_LOW = 0.6  # share of the last second below which it takes its real time again
# the nice value of a thread out of real time: the strongest normal priority, so CFS runs it
# at once on waking against work at nice 0 (weight 88 761 against 1 024). At nice 0, waiting
# its turn beside two busy loops, the line likely left a KickCAT scan without an answer for
# its 10 ms (tests/test_kickcat.py failed once in a clean clone's suite beside two `while True`
# loops; not reproduced in 3 runs of the test alone)
DEMOTED_NICE = -20


class RealTimeBudget:
    """The calling thread's real-time priority kept within the kernel's real-time bandwidth:
    `spent(now)` (wall clock, s) once per pass of the thread's loop. Once the thread has run
    more than BUDGET_HIGH of the last second it runs at normal priority, at DEMOTED_NICE
    (CFS: at once on waking, on a busy host too, and never the kernel's 50 ms stop),
    and once below BUDGET_LOW at the real-time priority it had again. Whatever priority the
    thread is given meanwhile (`answer_like_hardware` may come after its loop started) is
    what it goes back to; a thread at normal priority is left alone. `cpu_clock`: the
    thread's CPU time, s."""

    def __init__(self, now: float, cpu_clock: Callable[[], float] = time.thread_time):
        self.demotions = 0  # times the thread left real-time priority
        # taken away by us, to restore: (policy, its parameters, the thread's nice value)
        self._given: tuple[int, os.sched_param, int] | None = None
        self._thread = threading.get_native_id()  # setpriority takes a thread's own id
        self._cpu_clock = cpu_clock
        # the last BUDGET_WINDOWS windows' (wall time, CPU time) at their ends, oldest first
        self._marks: deque[tuple[float, float]] = deque([(now, cpu_clock())],
                                                        maxlen=BUDGET_WINDOWS + 1)

    def spent(self, now: float) -> None:
        marks = self._marks
        if now - marks[-1][0] < BUDGET_WINDOW:
            return
        cpu = self._cpu_clock()
        marks.append((now, cpu))
        since, cpu_since = marks[0]
        share = (cpu - cpu_since) / max(now - since, BUDGET_WINDOW * BUDGET_WINDOWS)
        try:
            if self._given is None:
                if share > BUDGET_HIGH:
                    policy = os.sched_getscheduler(0)
                    if policy in (os.SCHED_RR, os.SCHED_FIFO):
                        nice = os.getpriority(os.PRIO_PROCESS, self._thread)
                        self._given = policy, os.sched_getparam(0), nice
                        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
                        os.setpriority(os.PRIO_PROCESS, self._thread, DEMOTED_NICE)
                        self.demotions += 1
            elif share < BUDGET_LOW:
                policy, param, nice = self._given
                os.setpriority(os.PRIO_PROCESS, self._thread, nice)
                os.sched_setscheduler(0, policy, param)
                self._given = None
        except OSError:
            self._given = None  # no longer permitted: the thread stays as it is
