"""The control loop for a robot: every joint in one cycle.

Each period: one group sync (one SYNC per bus, every joint sampled in the same cycle), each
joint screened by its own safety net, the batched MPC over the joints that passed (one
compiled call), each decision checked by its net, one command per joint sent before the next
sync, and one `JointStates` message with every joint. A failure of any joint's drive ends the
run: the caller quick-stops every drive (`driver.drive_group.DriveGroup.quick_stop_all`), since
the other joints' plans assumed that one would move as planned.
"""

import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from controller import messages
from controller import workspace as ws
from controller.ilqr import CONVERGED, MAX_ITERATIONS, STATUS_NAMES
from controller.loop import CycleLoop, LoopOptions, LoopReport
from controller.messages import Subscriber
from controller.mpc import COLD, BatchMpc
from controller.policy import Decision, PlanSnapshot
from controller.reference import reference_at
from controller.safety import NOT_FINITE, BatchSafety, SafetyNet
from driver import DriveError, Sample
from driver.interface import SAMPLE_POSITION, SAMPLE_STATUSWORD, SAMPLE_T, SAMPLE_VELOCITY
from protocol import cia402

QUICK_STOPPED = "every joint quick-stopped, then disabled"  # what the caller does on failure
# the solver's status names by code, for a whole column at once
_STATUS_NAMES = np.array([STATUS_NAMES[code] for code in range(len(STATUS_NAMES))], dtype=object)


class Joints(Protocol):
    """What the loop needs of the drives (`driver.drive_group.DriveGroup`)."""

    names: list[str]

    def sync(self) -> np.ndarray:
        """This cycle's samples, a row per joint (`driver.interface.SAMPLE_*` columns)."""

    def command_currents(self, currents: Sequence[float]) -> None: ...

    def warnings(self) -> list[str]: ...

    def clock_trim(self) -> float:
        """s to move the next deadline by (0 unless a line keeps a clock of its own)."""


class _JointPolicy:
    """One joint of the batch as its safety net sees it: the net asks for the reference and
    tells the joint to start afresh; the batch itself is ticked by the loop, once."""

    def __init__(self, batch: BatchMpc, index: int):
        self._batch, self._index = batch, index
        joint = batch.joints[index]
        self.parameters = joint.parameters
        self.limits = joint.limits

    def tick(self, sample: Sample) -> Decision:
        raise TypeError("a batched joint is ticked by RobotLoop with the others")

    def reference_at(self, t: float) -> tuple[float, float]:
        q, qd = reference_at(self._batch.joints[self._index].reference_packed, t)
        return float(q), float(qd)

    def reset(self) -> None:
        self._batch.skip(self._batch.joints[self._index])

    def plan(self, t: float) -> PlanSnapshot:
        return self._batch.plan(self._batch.joints[self._index], t)


class RobotLoop(CycleLoop):
    """The cycle works on arrays over the joints (the samples stacked into one table, the MPC
    rows, the batch safety net): a handful of numpy operations a cycle whatever the number of
    joints, where a Python call per joint per field cost a millisecond for the whole TALOS.
    The per-joint nets remain for the rare joint the batch screens out, to name why."""

    def __init__(self, joints: Joints, batch: BatchMpc, options: LoopOptions,
                 subscribers: Sequence[Subscriber] = (),
                 dropped: Callable[[], int] = lambda: 0, stop: threading.Event | None = None,
                 settle: float = 0.0):
        """`settle` (s of drive time): tracking errors count from then on (the approach from
        where a joint rests to its reference is not tracking)."""
        if len(batch) != len(joints.names):
            raise ValueError(f"{len(joints.names)} joints, {len(batch)} problems")
        super().__init__(options, subscribers, dropped, stop)
        self._joints = joints
        self.batch = batch
        self.names = list(joints.names)
        count = len(batch)
        self._nets = [SafetyNet(_JointPolicy(batch, j)) for j in range(count)]
        self._safety = BatchSafety([joint.parameters for joint in batch.joints],
                                   [joint.limits for joint in batch.joints])
        self.failed_joint: str | None = None  # the joint whose failure ended the run
        # per joint: sum of squared tracking errors and their count (for tracking_rms)
        self._squared_error = np.zeros(count)
        self._tracked = 0
        self._settle = settle
        self.latest: np.ndarray | None = None  # the last cycle's samples, a row per joint
        self._enabled_names = [cia402.State.OPERATION_ENABLED.value] * count
        self._currents = np.zeros(count)
        self._header = np.zeros((count, ws.HEADER))
        self._status: list[str] = []
        self._fallbacks: dict[int, str] = {}  # joint -> why the net overrode it this cycle

    def _clock_trim(self) -> float:
        """An EtherCAT line on distributed clocks leads the cycle's clock."""
        return self._joints.clock_trim()

    def tracking_rms(self) -> list[float]:
        """rad, each joint's RMS of position minus reference over the run (after `settle`)."""
        if not self._tracked:
            return [math.nan] * len(self.names)
        return [float(v) for v in np.sqrt(self._squared_error / self._tracked)]

    def _cycle(self) -> "float | LoopReport":
        joints, batch, safety = self._joints, self.batch, self._safety
        exchange = time.perf_counter()
        try:
            table = self.latest = joints.sync()
            self._exchange_time = time.perf_counter() - exchange
        except DriveError as exc:
            return self._fail(exc, self.time + self.options.period)
        t = self._t = float(table[0, SAMPLE_T])
        for warning in joints.warnings():
            self.fault(t, "drive", warning, "continuing: the command does not use it")
        statuswords = table[:, SAMPLE_STATUSWORD].astype(np.int64)
        enabled = (statuswords & cia402.OPERATION_ENABLED_MASK) == cia402.OPERATION_ENABLED_BITS
        if not enabled.all():
            j = int(np.argmin(enabled))
            name, self.failed_joint = self.names[j], self.names[j]
            state = cia402.state_from_statusword(int(statuswords[j])).value
            return self._finish(1, f"joint {name}: drive left operation enabled: {state}",
                                "drive", QUICK_STOPPED, t)
        start = time.perf_counter()
        positions, velocities = table[:, SAMPLE_POSITION], table[:, SAMPLE_VELOCITY]
        rows = batch.rows
        believed = safety.believed(positions, velocities)
        fallbacks = self._fallbacks = {}
        if not believed.all():  # rare: the per-joint nets say why, and hold those joints
            for j in np.flatnonzero(~believed):
                sample = Sample(*table[j, :SAMPLE_STATUSWORD], int(table[j, SAMPLE_STATUSWORD]))
                fallbacks[int(j)] = self._nets[j].screen(sample).fault
        if fallbacks:
            rows[believed, ws.POSITION] = positions[believed]
            rows[believed, ws.VELOCITY] = velocities[believed]
        else:
            rows[:, ws.POSITION] = positions
            rows[:, ws.VELOCITY] = velocities
        cold = believed & (rows[:, ws.MODE] == COLD)
        if cold.any():  # a cold start begins from the current that holds the joint
            rows[cold, ws.INITIAL_CURRENT] = safety.hold_currents(positions)[cold]
        mpc_start = time.perf_counter()
        batch.run(t)
        self._mpc_time = time.perf_counter() - mpc_start
        header = self._header = rows[:, :ws.HEADER].copy()
        status = header[:, ws.STATUS]
        ok = (status == CONVERGED) | (status == MAX_ITERATIONS)
        planned = header[:, ws.PLANNED_CURRENT]
        currents = safety.checked_currents(positions, planned, ok)
        if fallbacks:  # a joint screened out: the net's command for it
            currents = np.where(believed, currents,
                                safety.screened_currents(positions, velocities))
        self._currents = currents
        self._status = _STATUS_NAMES[status.astype(np.intp)].tolist()
        failed = believed & ~(ok & np.isfinite(planned))
        if failed.any():
            for j in np.flatnonzero(failed):
                fallbacks[int(j)] = f"solver {self._status[j]}: holding position"
        for j in fallbacks:
            if not believed[j]:
                self._status[j] = NOT_FINITE
                header[j, ws.PLANNED_CURRENT] = math.nan
                header[j, ws.ITERATIONS] = 0
                header[j, ws.REFERENCE_POSITION] = self._nets[j].policy.reference_at(t)[0]
        decide_time = time.perf_counter() - start
        try:
            joints.command_currents(currents)
        except DriveError as exc:
            return self._fail(exc, t)
        return decide_time

    def _published(self, decide_time: float) -> None:
        t, table, header = self._t, self.latest, self._header
        fallback = np.zeros(len(self.names), dtype=bool)
        fallback[list(self._fallbacks)] = True
        self.publish(messages.joint_states(t, self.names, table, self._enabled_names,
                                           self._currents, header, self._status, fallback,
                                           decide_time))
        for j, why in self._fallbacks.items():
            self.report.fallbacks += 1
            self.fault(t, "controller", f"joint {self.names[j]}: {why}",
                       f"commanded {self._currents[j]:.3f} A (safe command)")
        if t >= self._settle:
            error = table[:, SAMPLE_POSITION] - header[:, ws.REFERENCE_POSITION]
            self._squared_error += error * error
            self._tracked += 1

    def _fail(self, exc: DriveError, t: float) -> LoopReport:
        self.failed_joint = getattr(exc, "joint", None)
        return self._finish(1, f"drive failed: {exc}", "drive", QUICK_STOPPED, t)
