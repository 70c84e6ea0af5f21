"""Real-time scheduling for a process of virtual drives, which stand in for hardware: a real
drive answers a SYNC or a frame within microseconds whatever the master's host is doing, so
the process that plays it must not wait behind CPU-bound work (another master starting up,
a compilation, a test's load), or the harness, not the master, is what a run measures."""

import os

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
