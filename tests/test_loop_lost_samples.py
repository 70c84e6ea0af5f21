"""A cycle whose sample never came (a frame lost on the line, ridden through) is skipped and
counted; the fault topic hears of a run of them when it starts and when samples come back,
not once a cycle: a real-time EtherCAT line rides through lost frames for up to its drives'
100 ms watchdog, some fifty cycles."""

import numpy as np

from controller.loop import ControlLoop, LoopOptions
from controller.mpc import Mpc
from driver.clock import DriveClock
from driver.interface import SampleLost
from model.parameters import load_model

MODEL = load_model()


class _LosingJoint:
    """One elbow at rest whose samples are lost at the cycles `lost` (1-based)."""

    names = ["elbow"]

    def __init__(self, lost: set[int]):
        self.lost = lost
        self.cycle = 0
        self.sampled = 0

    def sync(self) -> np.ndarray:
        self.cycle += 1
        if self.cycle in self.lost:
            raise SampleLost(f"the frame of cycle {self.cycle} did not come back")
        self.sampled += 1
        rest = MODEL.limits.position_min + 0.5
        return np.array([[self.sampled * 1e-3, rest, 0.0, 0.0, 0.0, 0x0237]])

    def command_currents(self, currents) -> None:
        pass

    def warnings(self) -> list[str]:
        return []

    def clock_trim(self) -> float:
        return 0.0


def test_a_run_of_lost_samples_is_two_fault_messages_and_every_one_counted():
    faults = []
    joints = _LosingJoint(lost={3, 4, 5, 6, 7, 10})
    loop = ControlLoop(joints, Mpc(MODEL), LoopOptions(clock=DriveClock(), duration=15e-3),
                       [lambda m: faults.append(m) if type(m).__name__ == "Fault" else None])
    report = loop.run()
    assert report.exit_code == 0
    assert report.lost_samples == 6 and report.missed_by_cause["late sample"] == 6
    said = [(f.cause, f.action) for f in faults]
    assert said == [
        ("the frame of cycle 3 did not come back",
         "cycle skipped: no decision, the drives hold their last command"),
        ("5 cycles in a row without a sample", "samples back: continuing"),
        ("the frame of cycle 10 did not come back",
         "cycle skipped: no decision, the drives hold their last command"),
    ]
