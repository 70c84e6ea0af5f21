"""Real-time scheduling for a process of virtual drives, which stand in for hardware: a real
drive answers a SYNC or a frame within microseconds whatever the master's host is doing, so
the process that plays it must not wait behind CPU-bound work (another master starting up,
a compilation, a test's load), or the harness, not the master, is what a run measures."""

import os
import time
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
# answers in microseconds whatever its host does, so the thread keeps its real-time share of
# every window below the kernel's, taking normal priority while it has used more.
BUDGET_WINDOW = 0.1  # s of wall time over which the thread's CPU time is looked at
BUDGET_HIGH = 0.8  # share of a window above which the thread leaves real-time priority
BUDGET_LOW = 0.5  # share of a window below which it takes its real-time priority again


class RealTimeBudget:
    """The calling thread's real-time priority kept within the kernel's real-time bandwidth:
    `spent(now)` (wall clock, s) once per pass of the thread's loop. After a window in which
    the thread ran more than BUDGET_HIGH of the time it runs at normal priority (CFS: on an
    idle CPU at once, on a busy host it waits its turn of a few ms, never the kernel's 50 ms
    stop), and after one below BUDGET_LOW at the real-time priority it had again. Whatever
    priority the thread is given meanwhile (`answer_like_hardware` may come after its loop
    started) is what it goes back to; a thread at normal priority is left alone.
    `cpu_clock`: the thread's CPU time, s."""

    def __init__(self, now: float, cpu_clock: Callable[[], float] = time.thread_time):
        self.demotions = 0  # windows after which the thread left real-time priority
        self._given: tuple[int, os.sched_param] | None = None  # taken away by us: restore
        self._cpu_clock = cpu_clock
        self._window_start = now
        self._cpu_start = cpu_clock()

    def spent(self, now: float) -> None:
        if now - self._window_start < BUDGET_WINDOW:
            return
        cpu = self._cpu_clock()
        share = (cpu - self._cpu_start) / (now - self._window_start)
        self._window_start, self._cpu_start = now, cpu
        try:
            if self._given is None:
                if share > BUDGET_HIGH:
                    policy = os.sched_getscheduler(0)
                    if policy in (os.SCHED_RR, os.SCHED_FIFO):
                        self._given = policy, os.sched_getparam(0)
                        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
                        self.demotions += 1
            elif share < BUDGET_LOW:
                os.sched_setscheduler(0, *self._given)
                self._given = None
        except OSError:
            self._given = None  # no longer permitted: the thread stays as it is
