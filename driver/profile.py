"""Which CiA 402 objects the master uses on a given drive, and their units, decided from the
drive's dictionary (its EDS) before anything is sent to it.

Standard objects first: cyclic synchronous torque (0x6060 = 10) with target torque 0x6071 in
per mille of rated torque 0x6076, current actual 0x6078 in per mille of rated current 0x6075
(or torque actual 0x6077), position 0x6064 and velocity 0x606C in encoder increments (0x608F,
or 2^19 per revolution when the EDS has none). Where the EDS offers the elbow drive's
manufacturer objects, the master uses them instead: cyclic synchronous current (-1) with target
0x2000 and motor current 0x2001 in mA, and the joint torque sensor 0x2002 (mN.m). A drive that
lacks what the loop needs is refused with every missing object named.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass

from canopen.objectdictionary import ObjectDictionary

from driver.interface import ProfileError
from protocol import objects
from protocol.dictionary import has, mapped_object, variable
from protocol.pdo import MappedObject


@dataclass(frozen=True)
class Profile:
    """The cyclic objects in the order the CiA 402 layer reads them. `inputs` is statusword,
    position, velocity, current feedback and, when the drive has a joint torque sensor, its
    reading; `outputs` is controlword and the target."""

    mode: int
    outputs: tuple[MappedObject, ...]
    inputs: tuple[MappedObject, ...]

    @property
    def target(self) -> MappedObject:
        return self.outputs[1]

    @property
    def current_feedback(self) -> MappedObject:
        return self.inputs[3]

    @property
    def has_joint_torque(self) -> bool:
        return len(self.inputs) > 4


@dataclass(frozen=True)
class Scaling:
    """Integer units of the cyclic objects to SI, read from the drive at bring-up."""

    rad_per_increment: float
    amps_per_feedback_unit: float  # current feedback (mA, or per mille of 0x6075 / 0x6076)
    target_units_per_amp: float  # target (mA, or per mille of rated torque)
    current_limit: float  # A, what the drive accepts (0x6073 x 0x6075, or 0x6072 via torque)
    joint_torque_per_unit: float = 1.0 / objects.MILLI  # 0x2002 in mN.m


def select_profile(dictionary: ObjectDictionary, drive_gain: float | None) -> Profile:
    """The profile for this dictionary; ProfileError naming every missing object."""
    missing = [f"0x{index:04X} ({name})" for index, name in (
        (objects.CONTROLWORD, "controlword"), (objects.STATUSWORD, "statusword"),
        (objects.POSITION_ACTUAL, "position actual"),
        (objects.VELOCITY_ACTUAL, "velocity actual")) if not _mappable(dictionary, index)]
    if not has(dictionary, objects.MODES_OF_OPERATION):
        missing.append("0x6060 (modes of operation)")
    manufacturer = (_mappable(dictionary, objects.TARGET_CURRENT)
                    and _mappable(dictionary, objects.MOTOR_CURRENT_ACTUAL))
    if manufacturer:
        mode = objects.MODE_CYCLIC_SYNC_CURRENT
        target, feedback = objects.TARGET_CURRENT, objects.MOTOR_CURRENT_ACTUAL
    else:
        mode, target = objects.MODE_CYCLIC_SYNC_TORQUE, objects.TARGET_TORQUE
        modes = variable(dictionary, objects.SUPPORTED_DRIVE_MODES)
        if modes is not None and modes.default is not None and not objects.supports_mode(
                modes.default, mode):
            missing.append("cyclic synchronous torque mode (0x6502 bit 9)")
        if not _mappable(dictionary, target):
            missing.append("0x6071 (target torque)")
        if not has(dictionary, objects.RATED_TORQUE):
            missing.append("0x6076 (motor rated torque)")
        if drive_gain is None or not drive_gain > 0:
            missing.append("the model's drive gain (torque per ampere) for 0x6071")
        if _mappable(dictionary, objects.CURRENT_ACTUAL) and has(dictionary,
                                                                 objects.RATED_CURRENT):
            feedback = objects.CURRENT_ACTUAL
        elif _mappable(dictionary, objects.TORQUE_ACTUAL):
            feedback = objects.TORQUE_ACTUAL
        else:
            feedback = None
            missing.append("0x6078 (current actual) with 0x6075, or 0x6077 (torque actual)")
    if not (has(dictionary, objects.MAX_CURRENT) and has(dictionary, objects.RATED_CURRENT)
            or has(dictionary, objects.MAX_TORQUE) and has(dictionary, objects.RATED_TORQUE)
            and drive_gain):
        missing.append("0x6073 (max current) with 0x6075, or 0x6072 (max torque) with 0x6076")
    if missing:
        raise ProfileError("drive lacks what the torque loop needs: " + ", ".join(missing))
    obj = _object_of(dictionary)
    inputs = [obj(objects.STATUSWORD), obj(objects.POSITION_ACTUAL),
              obj(objects.VELOCITY_ACTUAL), obj(feedback)]
    if _mappable(dictionary, objects.JOINT_TORQUE_SENSOR):
        inputs.append(obj(objects.JOINT_TORQUE_SENSOR))
    return Profile(mode, (obj(objects.CONTROLWORD), obj(target)), tuple(inputs))


def read_scaling(profile: Profile, read: Callable[[int, int], int],
                 dictionary: ObjectDictionary, drive_gain: float | None) -> Scaling:
    """Unit scaling from the drive's own values (read by SDO/CoE at bring-up)."""
    increments, revolutions = objects.ENCODER_INCREMENTS_PER_REV, 1
    if has(dictionary, objects.ENCODER_RESOLUTION, 1) and has(dictionary,
                                                             objects.ENCODER_RESOLUTION, 2):
        increments = read(objects.ENCODER_RESOLUTION, 1)
        revolutions = read(objects.ENCODER_RESOLUTION, 2)
        if increments <= 0 or revolutions <= 0:
            raise ProfileError(f"encoder resolution 0x608F = {increments}/{revolutions}: "
                               "expected positive increments per revolutions")
    rated_current = (read(objects.RATED_CURRENT, 0) / objects.MILLI
                     if has(dictionary, objects.RATED_CURRENT) else math.nan)
    rated_torque = (read(objects.RATED_TORQUE, 0) / objects.MILLI
                    if has(dictionary, objects.RATED_TORQUE) else math.nan)
    feedback = profile.current_feedback.index
    if feedback == objects.MOTOR_CURRENT_ACTUAL:
        per_unit = 1.0 / objects.MILLI
    elif feedback == objects.CURRENT_ACTUAL:
        per_unit = rated_current / objects.MILLI
    else:
        per_unit = rated_torque / objects.MILLI / drive_gain
    if profile.mode == objects.MODE_CYCLIC_SYNC_CURRENT:
        target_per_amp = objects.MILLI
    else:
        target_per_amp = objects.MILLI * drive_gain / rated_torque
    if has(dictionary, objects.MAX_CURRENT) and not math.isnan(rated_current):
        limit = read(objects.MAX_CURRENT, 0) / objects.MILLI * rated_current
    else:
        limit = read(objects.MAX_TORQUE, 0) / objects.MILLI * rated_torque / drive_gain
    for name, value in (("rated current 0x6075", rated_current),
                        ("rated torque 0x6076", rated_torque), ("current limit", limit)):
        if value <= 0:
            raise ProfileError(f"drive reports {name} = {value}: expected > 0")
    return Scaling(rad_per_increment=2.0 * math.pi * revolutions / increments,
                   amps_per_feedback_unit=per_unit, target_units_per_amp=target_per_amp,
                   current_limit=limit)


def _mappable(dictionary: ObjectDictionary, index: int) -> bool:
    var = variable(dictionary, index)
    return var is not None and var.pdo_mappable


def _object_of(dictionary: ObjectDictionary) -> Callable[[int], MappedObject]:
    return lambda index: mapped_object(variable(dictionary, index))
