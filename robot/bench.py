"""The master's own cost per cycle, for `bench --json`: what the service adds to the solver
on every cycle (the exchange with the drives, decoding, the safety screen, the MPC's inputs
and outputs, encoding), measured on a line of virtual slaves linked in this process
(`sim_bus.ethercat.linked`) with the slaves' own time taken out, so the figure is the
master's, not the harness's, and needs no root or hardware.

Joints are the elbow's model on one EtherCAT line (the shipped model: the bench needs no
robot file); the robot's cycle is `controller.loop.ControlLoop`, in lock-step."""

from pathlib import Path

import numpy as np

from controller.loop import ControlLoop, LoopOptions
from controller.mpc import BatchMpc, JointProblem
from controller.problem import OcpSettings
from driver.clock import DriveClock
from model import dynamics
from model.parameters import load_model
from robot.description import JointSpec, RobotSpec, default_reference, load_robot
from robot.problems import joint_problems
from robot.wiring import open_robot

# the robot whose own problem `bench` times beside the elbow-like joints: its lighter joints
# (wrists, grippers, head) made the in-loop tick five times the bench's 32 joints until the
# friction step was made resolvable (controller.problem.resolvable_friction_sharpness)
TALOS = Path(__file__).parent.parent / "robots" / "talos_32.toml"
MASTER_JOINT_COUNTS = (1, 7, 32)  # an elbow, an arm, the whole TALOS
LINE = "ethercat:bench0"  # a name only: the line is linked in this process
# the MPC is not what is measured: a short horizon keeps the bench quick (its call is
# excluded from the figure whatever its length)
BENCH_SETTINGS = OcpSettings(horizon=10)


def measure_master(joints: int, cycles: int) -> dict:
    """The master's cost per cycle (us, median and p99) for `joints` joints on one line,
    the cold first cycle excluded, and beside it the virtual slaves' time (not included)."""
    model = load_model()
    spec = RobotSpec(
        name=f"bench_{joints}", period_us=1000,
        joints=tuple(JointSpec(f"joint_{k}", LINE, k, model, None, {},
                               default_reference(model.limits)) for k in range(joints)),
        bitrates={}, source=Path(f"<{joints} elbows on one line>"))
    connection = open_robot(spec, sim=True, clock=DriveClock(), seed=0, period=1e-3)
    try:
        group = connection.group
        batch = BatchMpc([JointProblem(joint.model, BENCH_SETTINGS, reference=joint.reference)
                          for joint in spec.joints])
        loop = ControlLoop(group, batch, LoopOptions(period=1e-3, clock=DriveClock(),
                                                   duration=cycles * 1e-3))
        group.start()
        report = loop.run()
        line = group.drives[0].transport.line.master
        master_us = report.master.recent()
        # one exchange a cycle; the last ones are the measured cycles' (bring-up's came first)
        slaves_us = np.array(line.slave_seconds[-len(master_us):]) * 1e6
        own = master_us - slaves_us
    finally:
        connection.close()
    return {"joints": joints, "cycles": int(report.cycles),
            "master_median_us": round(float(np.median(own)), 2),
            "master_p99_us": round(float(np.percentile(own, 99)), 2),
            "virtual_slaves_median_us": round(float(np.median(slaves_us)), 2)}


def run(cycles: int = 3000) -> dict:
    """`bench --json`'s `master`: the master's own cost for 1, 7 and 32 joints."""
    return {str(joints): measure_master(joints, cycles) for joints in MASTER_JOINT_COUNTS}


def robot_problems(path: Path = TALOS) -> tuple[list[JointProblem], np.ndarray]:
    """A robot file's joints as `actuatord --robot` poses them at its default horizon and
    step (each joint's model, weights, friction sharpness and reference), and where the
    virtual drives start them: at rest (`model.dynamics.rest_position`)."""
    problems = joint_problems(load_robot(path))
    return problems, np.array([dynamics.rest_position(p.model.parameters.packed())
                               for p in problems])
