"""Each measurement on its own: the motor side (drive gain x current) and the joint torque
sensor are two instruments of one motion.

Both see the rigid body (inertia, gravity, payload); only the motor side sees the
transmission (friction and the effects in it) and the drive (the torque a current makes);
only the sensor sees its own gain and offset and the joint-side friction. So structure in one
residual that the other lacks says which side of the model, or which instrument, is wrong,
and structure in both points at what they share.

A baseline identified from both instruments at once (total least squares) spreads one side's
error over the parameters both share: with a saturating drive hidden, the first moments and
the sensor gain move too, and the sensor's residual would show structure that is not the
sensor's. So each side first gets its own linear parameters and its instrument's gain
refitted on its own residual (inertia, first moments, viscous and dry friction, offset, gain:
corrections, the inverse dynamics being linear in them; the payload, known, fixes the scale);
what that cannot absorb is a shape the side's model form lacks.
"""

import numpy as np

from model.gap.candidates import Problem
from model.gap.evidence import unit_columns
from model.gap.unexplained import structure

MOTOR_SIDE = ("motor_inertia", "first_moment_y", "first_moment_x", "viscous_friction_motor",
              "dry_friction_motor", "torque_offset_motor")
SENSOR_SIDE = ("link_inertia", "first_moment_y", "first_moment_x", "viscous_friction_joint",
               "dry_friction_joint", "torque_offset_joint")


def own_fit(problem: Problem, residual: np.ndarray, side: int) -> np.ndarray:
    """The residual of one side (0 motor, 1 sensor) after that side's linear parameters and
    its instrument's gain (a column of the measured torque) are refitted to it alone."""
    measured = (problem.s.motor_torque, problem.s.joint_torque)[side]
    columns = np.column_stack([
        unit_columns(problem.s, problem.parameters, (MOTOR_SIDE, SENSOR_SIDE)[side], side),
        measured])
    correction, *_ = np.linalg.lstsq(columns, residual, rcond=None)
    return residual - columns @ correction


def _summary(report: dict) -> dict:
    best = report["where"][0] if report["where"] else None
    return {"found": report["found"], "rmsd": report["rmsd"],
            "floor_estimate": report["floor_estimate"],
            "strongest_axis": best["axis"] if best else None,
            "strongest_gain": best["gain"] if best else None,
            "drift": report["drift"] if report["drift"]["found"] else None}


def verdict(motor: bool, sensor: bool) -> str:
    """Which side is wrong, from whether each instrument's residual has structure."""
    if motor and sensor:
        return ("both instruments disagree with the model: what they share is wrong (inertia, "
                "gravity, payload), or each side has its own error")
    if motor:
        return ("the motor side is wrong: drive gain x current has structure the torque sensor "
                "lacks, so the transmission (friction and the like) or the drive (the torque a "
                "current makes) misses something; the rigid body agrees with the torque sensor")
    if sensor:
        return ("the torque sensor side is wrong: its residual has structure the motor side "
                "lacks, so the sensor (gain, offset, nonlinearity) or the joint-side friction "
                "is off; the motor side agrees with the model")
    return "both instruments agree with the model"


def instruments(problem: Problem, motor_before: np.ndarray, motor_after: np.ndarray,
                sensor: np.ndarray, named: bool) -> dict:
    """The `instruments` report section: each residual's structure (after its own side's
    refit) and what it says. `named`: library effects were found, all of which act on the
    motor side, so its residual had structure before them even where no map resolves it (a
    ripple of many periods)."""
    before, after, joint = (structure(problem, own_fit(problem, r, side)) for r, side in
                            ((motor_before, 0), (motor_after, 0), (sensor, 1)))
    return {
        "motor_before": _summary(before),
        "motor_after": _summary(after),
        "sensor": {**_summary(joint), "where": joint["where"]},
        "verdict_before": verdict(before["found"] or named, joint["found"]),
        "verdict_after": verdict(after["found"], joint["found"]),
        "method": "the structure search of `unexplained` run on each residual apart, after "
                  "refitting that side's own linear parameters to it: the motor side (the "
                  "torque the measured current makes, less the model's motor torque) before "
                  "and after the named effects, and the joint torque sensor (less the model's "
                  "joint torque, which the effects do not change)",
    }
