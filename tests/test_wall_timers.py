"""The wall clock's periodic jobs (`driver.clock.WallTimers`): every party's in one thread,
on the grid of their interval, a failing job dropped without stopping the others, a stopped
job never run again. Timing is only bounded from below (a busy host runs them late)."""

import math
import threading
import time

from driver.clock import WallTimers
from tests.conftest import wait_for

INTERVAL = 0.01  # s


def test_jobs_of_many_parties_run_in_one_thread_on_their_interval_grid():
    runs: dict[int, list[tuple[float, str]]] = {0: [], 1: [], 2: []}
    stops = [WallTimers().every(INTERVAL, lambda now, k=k: runs[k].append(
        (now, threading.current_thread().name))) for k in runs]
    try:
        assert wait_for(lambda: all(len(r) >= 5 for r in runs.values()), 5.0)
    finally:
        for stop in stops:
            stop()
    threads = {name for r in runs.values() for _, name in r}
    assert threads == {"wall-timers"}
    for r in runs.values():  # once per grid point at most, however late it ran
        points = [math.floor(now / INTERVAL + 1e-9) for now, _ in r]
        assert points == sorted(set(points))
    # the three parties' runs fall on the same grid points: one wake-up for all of them
    assert {round(now / INTERVAL) for now, _ in runs[0][1:4]} <= {
        round(now / INTERVAL) for now, _ in runs[1]}


def test_a_failing_job_is_dropped_and_the_others_run_on():
    ran, failed = [], []

    def fails(now: float) -> None:
        failed.append(now)
        raise RuntimeError("a job's own bug")

    stop_fails = WallTimers().every(INTERVAL, fails)
    stop_ok = WallTimers().every(INTERVAL, ran.append)
    try:
        assert wait_for(lambda: len(ran) >= 5, 5.0)
    finally:
        stop_fails()
        stop_ok()
    assert len(failed) == 1


def test_a_stopped_job_runs_no_more():
    ran: list[float] = []
    stop = WallTimers().every(INTERVAL, ran.append)
    assert wait_for(lambda: len(ran) >= 2, 5.0)
    stop()
    time.sleep(2 * INTERVAL)  # a run already under way when it stopped ends
    count = len(ran)
    time.sleep(5 * INTERVAL)
    assert len(ran) == count
