"""A run says why it missed cycles: each miss is put down to the phase that took the cycle's
time (a late wake-up, a late sample, a decision over budget, the telemetry), so a user can tell
their machine from the service. Real time with a virtual drive in this process; the slow
phase is made twenty periods long so that it, not the host, is what the run measures."""

import itertools
import time

import pytest

from controller.loop import DECISION, LATE_SAMPLE, ControlLoop, LoopOptions
from controller.policy import Decision
from driver.drive_group import single_joint
from model.parameters import load_model
from sim_bus.plant import SensorNoise
from tests.conftest import as_a_real_time_master, virtual_pair

MODEL = load_model()
STALL = 0.02  # s: twenty periods
EVERY = 50  # cycles between stalls


class _Holding:
    """Holds the joint with a fixed current; every EVERY-th decision (or sample) stalls."""

    parameters, limits = MODEL.parameters, MODEL.limits

    def __init__(self):
        self.ticks = 0

    def tick(self, sample) -> Decision:
        self.ticks += 1
        if self.ticks % EVERY == 0:
            time.sleep(STALL)
        return Decision(0.0, sample.position, 0.0, "held", True)

    def reference_at(self, t: float) -> tuple[float, float]:
        return 0.0, 0.0

    def reset(self) -> None:
        pass

    def plan(self, t: float) -> None:
        return None


@pytest.mark.real_time
def test_a_slow_decision_is_named_as_the_cause_of_its_missed_cycles():
    # at the master's priority, as actuatord runs: at normal priority on a loaded host (load 3)
    # the host's own late wake-ups and samples outnumbered the stalls (230 and 221 vs 224)
    with virtual_pair(lockstep=False, noise=SensorNoise()) as (_, drive), \
            as_a_real_time_master():
        drive.start()
        report = ControlLoop(single_joint(drive), _Holding(), LoopOptions(duration=0.4)).run()
    causes = report.missed_by_cause
    stalled = (report.cycles // EVERY) * STALL / 1e-3  # cycles the stalls took
    # the host adds misses of its own (late wake-ups on a busy machine), never fewer
    assert causes[DECISION] >= 0.5 * stalled and max(causes, key=causes.get) == DECISION, (
        causes)
    assert sum(causes.values()) == report.missed_cycles


def slow_sample(group):
    """`group` (one bus) with its sample late every EVERY-th cycle: the bus's exchange stalls
    before its SYNC goes out (as a drive's `sync` stalled when a joint had its own)."""
    segment = group.segments[0]
    trigger, cycles = segment.trigger, itertools.count(1)

    def stalling_trigger():
        if next(cycles) % EVERY == 0:
            time.sleep(STALL)
        trigger()

    segment.trigger = stalling_trigger
    return group


@pytest.mark.real_time
def test_a_late_sample_is_named_as_the_cause_of_its_missed_cycles():
    with virtual_pair(lockstep=False) as (_, drive), as_a_real_time_master():
        drive.start()
        report = ControlLoop(slow_sample(single_joint(drive)), _Holding(),
                             LoopOptions(duration=0.4)).run()
    causes = report.missed_by_cause
    stalled = (report.cycles // EVERY) * STALL / 1e-3
    assert causes[LATE_SAMPLE] >= 0.5 * stalled and max(causes, key=causes.get) == LATE_SAMPLE, (
        causes)
    assert sum(causes.values()) == report.missed_cycles
