"""A segment's once-a-cycle looks (driver.drive_group): a bus or line looks at its drives'
faults and warnings through one flag and their warning lists at once, not a call per drive per
cycle; what a drive reports between two cycles still reaches the next one, naming its joint."""

from pathlib import Path

import numpy as np
import pytest

from driver.clock import DriveClock
from driver.drive_group import CanOpenBus, EthercatLine, JointFailure
from driver.interface import SAMPLE_JOINT_TORQUE, DriveFault, EncoderGlitch
from model.parameters import load_model
from robot.description import JointSpec, RobotSpec, default_reference
from robot.wiring import open_robot
from sim_bus.faults import Fault

MODEL = load_model()


def _robot(bus: str, joints: int, faults=()):
    """`joints` elbows on one bus (CANopen node ids from 1, EtherCAT positions from 0), their
    virtual drives in this process (`faults` scheduled), started."""
    first = 0 if bus.startswith("ethercat") else 1
    spec = RobotSpec(
        name="looks", period_us=1000,
        joints=tuple(JointSpec(f"joint_{k}", bus, first + k, MODEL, None, {},
                               default_reference(MODEL.limits)) for k in range(joints)),
        bitrates={}, source=Path("<test>"))
    connection = open_robot(spec, sim=True, clock=DriveClock(), seed=0, period=1e-3,
                            response_timeout=1.0, faults=faults)
    connection.group.start()
    return connection


def _cycles(group, count: int) -> None:
    for _ in range(count):
        group.sync()
        group.command_currents(np.zeros(len(group)))


def test_a_drive_fault_between_cycles_stops_the_line_at_its_next_look_naming_the_joint():
    connection = _robot("ethercat:looks0", 3)
    try:
        group = connection.group
        [line] = group.segments
        assert isinstance(line, EthercatLine)
        _cycles(group, 5)
        group.drives[1].fail(DriveFault("joint_1's drive: injected", 0x2310))
        with pytest.raises(JointFailure, match="joint joint_1: joint_1's drive: inj") as raised:
            group.sync()
        assert raised.value.joint == "joint_1"
        # and on the command's side, for a fault that comes after the cycle's sample
        group.drives[1].enable()
        _cycles(group, 3)
        group.sync()
        group.drives[2].fail(DriveFault("joint_2's drive: injected", 0x2310))
        with pytest.raises(JointFailure, match="joint joint_2") as raised:
            group.command_currents(np.zeros(3))
        assert raised.value.joint == "joint_2"
    finally:
        connection.close()


def test_a_drive_warning_between_cycles_reaches_the_next_look_once_naming_the_joint():
    connection = _robot("can0", 2)
    try:
        group = connection.group
        [bus] = group.segments
        assert isinstance(bus, CanOpenBus)
        _cycles(group, 5)
        assert group.warnings() == []
        # a TPDO of the wrong size for the second drive, as its transport reports one
        cycle = group.drives[1].transport.bus_cycle
        cob_id = next(cob for cob, (row, *_) in cycle._tpdos.items()
                      if row == group.drives[1].transport.row)
        cycle._on_tpdo(cob_id, bytearray(1), 0.0)
        _cycles(group, 1)
        [warning] = group.warnings()
        assert warning.startswith(f"joint joint_1: TPDO 0x{cob_id:03X} with 1 bytes")
        assert group.warnings() == []  # said once
    finally:
        connection.close()


def test_a_lines_image_names_a_saturated_sensor_a_glitch_and_a_tripped_drive_by_joint():
    """The line's image decoded in one compiled call: its rare outcomes still in the drives'
    own words, each naming its joint (the second of three)."""
    for fault, expected in ((Fault.TORQUE_SENSOR_SATURATED, None),
                            (Fault.ENCODER_GLITCH, EncoderGlitch),
                            (Fault.OVERCURRENT_TRIP, DriveFault)):
        connection = _robot("ethercat:looks0", 3, [("joint_1", fault, 0.01)])
        try:
            group = connection.group
            unread, warnings = np.zeros(3, dtype=bool), []
            with pytest.raises(JointFailure) if expected else _nothing() as raised:
                for _ in range(30):
                    table = group.sync()
                    unread |= np.isnan(table[:, SAMPLE_JOINT_TORQUE])
                    warnings += group.warnings()
                    group.command_currents(np.zeros(3))
            if expected is None:  # a warning, the joint's reading held out of its samples
                assert unread.tolist() == [False, True, False]
                assert warnings and all(
                    w.startswith("joint joint_1: joint torque sensor reading saturated")
                    for w in warnings), warnings
            else:
                assert raised.value.joint == "joint_1"
                assert isinstance(raised.value.cause, expected), raised.value.cause
        finally:
            connection.close()


class _nothing:
    """No exception expected: a context that lets the block run."""

    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False
