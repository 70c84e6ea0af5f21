"""A virtual line's thread keeps within the kernel's real-time bandwidth (`sim_bus.priority.
RealTimeBudget`): a last second busier than BUDGET_HIGH takes it to normal priority, a quiet
one back to the real-time priority it was given. Driven by a CPU clock the test advances, so the
windows' shares are exact whatever the host is doing; the thread's policy is the kernel's."""

import os
import threading

import pytest

from sim_bus.priority import (
    BUDGET_HIGH,
    BUDGET_LOW,
    BUDGET_WINDOW,
    BUDGET_WINDOWS,
    DEMOTED_NICE,
    RealTimeBudget,
)


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


def _policies(shares: list[float]) -> list[tuple[int, int]]:
    """The thread's policy and nice value after each window of `shares` (its CPU time / wall
    time), the thread at SCHED_RR 3 and nice 0 to begin with."""
    os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(3))
    cpu = [0.0]
    now = 100.0
    budget = RealTimeBudget(now, cpu_clock=lambda: cpu[0])
    step = BUDGET_WINDOW * 1.01  # a window, however the sums round
    seen = []
    for share in shares:
        budget.spent(now + step / 2)  # mid-window: nothing is looked at
        now += step
        cpu[0] += share * step
        budget.spent(now)
        seen.append((os.sched_getscheduler(0),
                     os.getpriority(os.PRIO_PROCESS, threading.get_native_id())))
    return seen


def _expected(shares: list[float]) -> list[int]:
    """The rule on its own: the mean share of the last BUDGET_WINDOWS windows (of the
    windows so far, over a whole second, at the start) above BUDGET_HIGH leaves real time,
    below BUDGET_LOW takes it again."""
    real_time, seen = True, []
    for k in range(len(shares)):
        share = sum(shares[max(0, k + 1 - BUDGET_WINDOWS):k + 1]) / BUDGET_WINDOWS
        if real_time and share > BUDGET_HIGH:
            real_time = False
        elif not real_time and share < BUDGET_LOW:
            real_time = True
        seen.append(os.SCHED_RR if real_time else os.SCHED_OTHER)
    return seen


@pytest.mark.root
@pytest.mark.real_time
def test_a_second_over_the_share_leaves_real_time_priority_and_a_quiet_one_takes_it_back():
    # cycling just under the share for a long while, busy until it is over, then idle (0.97,
    # not 1: no mean of the last second falls on a threshold, where rounding would decide)
    shares = [BUDGET_HIGH - 0.05] * (2 * BUDGET_WINDOWS) + [0.97] * BUDGET_WINDOWS + [
        0.0] * BUDGET_WINDOWS

    def job():
        try:
            return _policies(shares), os.sched_getparam(0).sched_priority
        except PermissionError:
            pytest.skip("no permission for SCHED_RR (run as root)")
        finally:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))

    seen, priority = _in_a_thread(job)
    expected = _expected(shares)
    # out of real time at the strongest normal priority, back at nice 0 after
    assert seen == [(policy, 0 if policy == os.SCHED_RR else DEMOTED_NICE)
                    for policy in expected]
    # the thread left real time once, well into the busy second, and took it back once
    changes = [k for k in range(1, len(seen)) if seen[k] != seen[k - 1]]
    assert len(changes) == 2
    assert 2 * BUDGET_WINDOWS < changes[0] < 3 * BUDGET_WINDOWS < changes[1]
    assert seen[-1] == (os.SCHED_RR, 0) and priority == 3


def test_a_thread_at_normal_priority_is_left_alone():
    def job():
        cpu = [0.0]
        budget = RealTimeBudget(0.0, cpu_clock=lambda: cpu[0])
        for k in range(1, 2 * BUDGET_WINDOWS):  # two whole seconds busy
            cpu[0] = k * BUDGET_WINDOW * 1.01
            budget.spent(cpu[0])
        return os.sched_getscheduler(0), budget.demotions

    assert _in_a_thread(job) == (os.SCHED_OTHER, 0)
