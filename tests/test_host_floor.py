"""The floor beside a run (`driver.host_floor.FloorBeside`): how its stalls become missed
cycles over a run's span, and that its loops run where and while they are asked to."""

import os
import threading
import time

import pytest

from driver.host_floor import FloorBeside, Stall, host_steal_s


def _floor(stalls: list[Stall]) -> FloorBeside:
    floor = FloorBeside([0, 1], period=1e-3)
    floor.stalls = stalls
    return floor


def test_stalls_count_the_deadlines_they_skipped_and_overlaps_count_once():
    floor = _floor([Stall(0, 10.0, 10.0025),     # 2.5 periods: 2 deadlines skipped
                    Stall(1, 20.0, 20.004),      # 4 on one CPU ...
                    Stall(0, 20.002, 20.0065),   # ... overlapping 4.5 on the other: 6.5 in all
                    Stall(1, 30.0, 30.0009)])    # under a period: recorded, never counted
    figures = floor.figures(0.0, 100.0)
    assert figures["missed"] == 2 + 6 + 0
    assert figures["missed_percent"] == pytest.approx(100 * 8 / 100_000, abs=1e-3)
    assert figures["longest_stall_ms"] == pytest.approx(6.5)
    assert figures["cpus"] == [0, 1]


def test_only_the_runs_span_counts():
    floor = _floor([Stall(0, 1.0, 1.050), Stall(0, 5.0, 5.003), Stall(1, 8.9, 9.02)])
    # the first stall ended before the span began; the last is cut at its end
    figures = floor.figures(2.0, 9.0)
    assert figures["missed"] == 3 + 100
    assert figures["missed_percent"] == pytest.approx(100 * 103 / 7000, abs=1e-3)


@pytest.mark.real_time
def test_the_loops_run_on_their_cpus_until_the_block_ends():
    cpus = sorted(os.sched_getaffinity(0))
    with FloorBeside(cpus) as floor:
        time.sleep(0.05)
        names = {t.name for t in threading.enumerate()}
        assert {f"floor-beside-{cpu}" for cpu in cpus} <= names
    assert not {t.name for t in threading.enumerate()} & {f"floor-beside-{c}" for c in cpus}
    assert floor.figures(0.0, 1.0)["cpus"] == cpus
    if os.geteuid() != 0:  # no real-time priority: said, not hidden
        assert floor.refused


def test_the_hosts_steal_is_read_per_cpu():
    steal = host_steal_s()
    if not os.path.exists("/proc/stat"):
        assert steal == {}
        return
    assert set(steal) == set(range(os.cpu_count()))
    assert all(value >= 0 for value in steal.values())


def test_a_runs_misses_are_put_down_to_the_stalls_beside_them():
    floor = _floor([Stall(0, 10.0, 10.0045), Stall(1, 20.0, 20.0012)])
    explained = floor.in_stalls([
        (10.005, 4),    # found just after the first stall: explained
        (15.0, 1),      # nothing near: the run's own
        (20.003, 1),    # a cycle that overran through the second stall's end: explained
        (20.5, 2),      # well after it: the run's own
        (9.9, 1),       # before any stall began
    ])
    assert explained == 4 + 1


def test_the_longest_stall_before_a_failure_is_named():
    floor = _floor([Stall(0, 10.0, 10.0047), Stall(1, 10.03, 10.0322), Stall(1, 9.0, 9.5)])
    # a run that failed at 10.05: the 4.7 ms stall of CPU 0 45.3 ms before its end
    assert floor.longest_stall(9.95, 10.05) == {"cpu": 0, "ms": 4.7, "ended_ms_before": 45.3}
    assert floor.longest_stall(10.031, 10.05)["cpu"] == 1   # only the later one overlaps
    assert floor.longest_stall(11.0, 12.0) is None
