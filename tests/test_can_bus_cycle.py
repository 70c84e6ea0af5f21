"""A CAN bus owns its cycle (issue 22 items 1 and 4): one SYNC a cycle for every drive on it,
each drive's TPDOs decoded from the bus's image as the drive itself decodes them, drive time
advanced by a period per SYNC, and a failure named by the joint whose drive it concerns."""

import numpy as np
import pytest

from driver.canopen_transport import CanOpenTransport
from driver.cia402_drive import Cia402Drive
from driver.clock import DriveClock
from driver.drive_group import CanOpenBus, DriveGroup, JointFailure
from driver.interface import (
    SAMPLE_JOINT_TORQUE,
    SAMPLE_MOTOR_CURRENT,
    SAMPLE_POSITION,
    SAMPLE_STATUSWORD,
    SAMPLE_VELOCITY,
    DriveTimeout,
)
from model.parameters import Payload, load_model
from protocol import cia301
from sim_bus.embedded import EmbeddedBus
from sim_bus.plant import SensorNoise

MODEL = load_model()
NODES = (2, 3)


def two_drives_on_one_bus(clock: DriveClock, response_timeout: float = 1.0):
    """Two virtual drives on one in-process bus and the master's group over them."""
    link = EmbeddedBus(clock=DriveClock())  # the drives' own time, as `--sim` gives them
    for node in NODES:
        link.add_drive(MODEL, Payload(), SensorNoise(seed=node), node, commissioned=True)
    joints = []
    for node in NODES:
        transport = CanOpenTransport(link.master_network, node, clock=clock,
                                     response_timeout=response_timeout, owns_network=False)
        joints.append((f"joint{node}", Cia402Drive(
            transport, velocity_limit=MODEL.limits.velocity_max,
            drive_gain=MODEL.parameters.drive_gain)))
    group = DriveGroup([name for name, _ in joints],
                       [CanOpenBus("bus", link.master_network, joints)])
    return link, group


def test_one_sync_a_cycle_each_row_decoded_as_its_drive_does_and_drive_time_per_sync():
    clock = DriveClock()
    link, group = two_drives_on_one_bus(clock)
    syncs = []
    link.network.subscribe(cia301.SYNC_COB_ID, lambda *frame: syncs.append(frame))
    try:
        group.start()
        before, started = len(syncs), clock.now()
        currents = np.array([0.3, -0.3])
        for _ in range(50):
            table = group.sync()
            group.command_currents(currents)
        assert len(syncs) - before == 50  # one SYNC for both drives
        assert clock.now() - started == pytest.approx(50e-3, abs=1e-12)
        bus = group.drives[0].transport.bus_cycle
        for j, drive in enumerate(group.drives):
            # the drive's own decoding of its row (`Cia402Drive.take`, the per-joint path)
            sample = drive.take(lambda drive=drive: bus.inputs(drive.transport.row))
            assert table[j, SAMPLE_POSITION] == sample.position
            assert table[j, SAMPLE_VELOCITY] == sample.velocity
            assert table[j, SAMPLE_MOTOR_CURRENT] == sample.motor_current
            assert table[j, SAMPLE_JOINT_TORQUE] == sample.joint_torque
            assert table[j, SAMPLE_STATUSWORD] == sample.statusword
        # each drive got its own command, encoded in the bus's one pass
        assert table[:, SAMPLE_MOTOR_CURRENT] == pytest.approx(currents, abs=0.05)
    finally:
        group.close()
        link.close()


def test_a_drive_that_stops_answering_is_named_by_its_joint():
    link, group = two_drives_on_one_bus(DriveClock(), response_timeout=0.05)
    try:
        group.start()
        group.sync()
        link.nodes[1].go_silent()
        with pytest.raises(JointFailure) as failure:
            group.sync()
        assert failure.value.joint == "joint3"
        assert isinstance(failure.value.cause, DriveTimeout)
        assert "no TPDO 0x183, 0x283, 0x383 within 50 ms" in str(failure.value)
    finally:
        group.close()
        link.close()
