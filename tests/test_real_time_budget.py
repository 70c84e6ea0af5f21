"""A virtual line's thread keeps within the kernel's real-time bandwidth (`sim_bus.priority.
RealTimeBudget`): a window busier than BUDGET_HIGH takes it to normal priority, a quiet one
back to the real-time priority it was given. Driven by a CPU clock the test advances, so the
windows' shares are exact whatever the host is doing; the thread's policy is the kernel's."""

import os
import threading

import pytest

from sim_bus.priority import BUDGET_HIGH, BUDGET_LOW, BUDGET_WINDOW, RealTimeBudget


def _in_a_thread(job):
    """`job()` in a thread of its own (the budget acts on the calling thread); its result or
    its exception."""
    result: dict = {}

    def run():
        try:
            result["value"] = job()
        except BaseException as exc:  # handed to the test's thread
            result["error"] = exc

    thread = threading.Thread(target=run)
    thread.start()
    thread.join(10)
    if "error" in result:
        raise result["error"]
    return result["value"]


@pytest.mark.root
def test_a_busy_window_leaves_real_time_priority_and_a_quiet_one_takes_it_back():
    def job():
        try:
            os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(3))
        except PermissionError:
            pytest.skip("no permission for SCHED_RR (run as root)")
        cpu = [0.0]
        now = 100.0
        budget = RealTimeBudget(now, cpu_clock=lambda: cpu[0])
        seen = []

        step = BUDGET_WINDOW * 1.01  # a window, however the sums round

        def window(share: float) -> None:
            nonlocal now
            now += step
            cpu[0] += share * step
            budget.spent(now)
            seen.append(os.sched_getscheduler(0))

        window(BUDGET_HIGH - 0.05)  # busy, but within the share: stays real-time
        budget.spent(now + BUDGET_WINDOW / 2)  # mid-window: nothing is looked at
        window(BUDGET_HIGH + 0.1)  # over it: normal priority
        window(BUDGET_LOW + 0.1)  # between the two: stays normal
        window(BUDGET_LOW - 0.1)  # quiet: back to the priority it was given
        param = os.sched_getparam(0).sched_priority
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        return seen, param, budget.demotions

    seen, param, demotions = _in_a_thread(job)
    assert seen == [os.SCHED_RR, os.SCHED_OTHER, os.SCHED_OTHER, os.SCHED_RR]
    assert param == 3 and demotions == 1


def test_a_thread_at_normal_priority_is_left_alone():
    def job():
        cpu = [0.0]
        budget = RealTimeBudget(0.0, cpu_clock=lambda: cpu[0])
        cpu[0] = BUDGET_WINDOW  # a whole window busy
        budget.spent(BUDGET_WINDOW)
        return os.sched_getscheduler(0), budget.demotions

    assert _in_a_thread(job) == (os.SCHED_OTHER, 0)
