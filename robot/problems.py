"""A robot's joints as the MPC poses them: one optimal control problem per joint.

`actuatord --robot` and `bench` (which times the robot's own problem) build them here, so the
bench measures the problems the service solves."""

import dataclasses

from controller.mpc import JointProblem
from controller.problem import OcpSettings
from robot.description import RobotSpec


def joint_problems(robot: RobotSpec, settings: OcpSettings | None = None,
                   weights: dict[str, float] | None = None) -> list[JointProblem]:
    """One problem per joint: `settings` (horizon, step; the defaults' when None) with the
    cost weights `weights` (the command line's) and the joint's own from the robot file on
    top, the joint's friction sharpness and its reference. A weight the problem refuses is
    a ValueError naming the joint."""
    settings = settings or OcpSettings()
    problems = []
    for joint in robot.joints:
        try:
            joint_settings = settings.with_weights(**{**(weights or {}), **joint.weights})
            if joint.friction_sharpness is not None:
                joint_settings = dataclasses.replace(
                    joint_settings, friction_sharpness=joint.friction_sharpness)
            joint_settings.check_weights()
        except ValueError as exc:
            raise ValueError(f"joint {joint.name}: {exc}") from None
        problems.append(JointProblem(joint.model, joint_settings, reference=joint.reference))
    return problems
