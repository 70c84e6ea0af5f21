"""In lock-step every watchdog counts drive time (cycles), never the wall clock: a slow or busy
host trips none, and a real loss is found on the same cycle in every run."""

import time

import pytest

from driver import DriveLost
from tests.conftest import virtual_pair


def cycles_until_lost(stop_heartbeat_at: int, host_pause: float) -> int:
    """Run lock-step cycles, pausing the host `host_pause` s every 50 cycles, stop the drive's
    heartbeat at `stop_heartbeat_at`; the cycle in which the drive was declared lost."""
    with virtual_pair() as (sim, master):
        master.start()
        for cycle in range(1, 2000):
            if cycle == stop_heartbeat_at:
                sim.stop_heartbeat()
            if cycle % 50 == 0:
                time.sleep(host_pause)  # a busy host: wall time passes, drive time does not
            try:
                master.sync()
                master.command_current(0.0)
            except DriveLost as exc:
                assert "heartbeat missing for 201 cycles (0.201 s of drive time)" in str(exc)
                return cycle
    pytest.fail("the heartbeat loss was never noticed")


def test_wall_clock_pauses_trip_no_watchdog_and_the_loss_falls_on_the_same_cycle():
    # 0.25 s pauses are 2.5 heartbeat periods of wall time: a wall-clock consumer trips
    paused = cycles_until_lost(450, host_pause=0.25)
    fast = cycles_until_lost(450, host_pause=0.0)
    assert paused == fast
    # last beat at cycle 400 (every 100 cycles), lost when 200 cycles passed without one
    assert paused == 600


def test_the_drives_own_time_in_lockstep_is_its_cycles_and_its_jobs_fall_on_them():
    """A virtual drive's watchdogs run on the time its clock makes (`driver.clock`): in
    lock-step the SYNCs it took, so a 100 ms job of a 1 kHz drive runs on every 100th cycle
    exactly (never the 101st by a float sum's rounding), none between, none once stopped."""
    from driver.clock import DriveClock

    time_ = DriveClock().timers()
    ran: list[tuple[int, float]] = []
    cycle = 0
    stop = time_.every(0.1, lambda now: ran.append((cycle, now)))
    for cycle in range(1, 1001):  # the job reads `cycle`
        time_.tick(1e-3)
        if cycle == 700:
            stop()
    assert [c for c, _ in ran] == [100, 200, 300, 400, 500, 600, 700]
    assert ran[-1][1] == pytest.approx(0.7, abs=1e-12)
    booted = []
    time_.later(0.01, lambda: booted.append(time_.now()))  # a reset's boot-up: before any
    assert booted == [pytest.approx(1.0, abs=1e-12)]  # cycle can look, no time passing
