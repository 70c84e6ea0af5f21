"""`sim-bus` in its own process on udp_multicast; our master and a generic canopen master."""

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import canopen
import numpy as np
import pytest

from driver.canopen_drive import CanOpenDrive
from model import dynamics
from model.dynamics import SUBSTEPS
from model.parameters import load_model
from protocol import eds_path, objects
from protocol.cia402 import State, state_from_statusword
from tests.conftest import sim_bus_process, udp_bus_spec
from tests.test_drive_virtual_bus import HALF_COUNT, current_profile

pytestmark = pytest.mark.subprocess  # runs the commands as processes


@pytest.mark.real_time
def test_master_drives_sim_bus_process_and_motion_matches_the_model():
    bus = udp_bus_spec()
    with sim_bus_process(bus, "--node-id", "3"):
        master = CanOpenDrive.open(bus, 3, velocity_limit=load_model().limits.velocity_max)
        try:
            master.start()
            first = master.sync()
            currents = current_profile(1500)
            samples = []
            for current in currents:
                master.command_current(float(current))
                samples.append(master.sync())
        finally:
            master.close()
    applied = np.round(currents * 1000) / 1000
    params = load_model().parameters.packed()
    expected = dynamics.simulate(first.position, first.velocity, applied, params, 1e-3,
                                 SUBSTEPS)
    measured = np.array([s.position for s in samples])
    # the first sample is itself quantised, so allow one count on top of this run's rounding
    assert np.max(np.abs(measured - expected[:, 0])) <= 3 * HALF_COUNT
    assert np.ptp(measured) > 0.2


@pytest.mark.real_time
def test_generic_canopen_master_drives_sim_bus_in_cyclic_synchronous_torque_mode():
    """canopen's RemoteNode with the shipped EDS and nothing of ours: CiA 402 by the book."""
    bus = udp_bus_spec()
    _, _, group_port = bus.partition(":")
    group, port = group_port.split(":")
    network = canopen.Network()
    network.connect(interface="udp_multicast", channel=group, port=int(port))
    try:
        node = network.add_node(2, str(eds_path()))
        with sim_bus_process(bus):
            # listen before resetting: the boot-up answer can beat a late listener
            waiter = ThreadPoolExecutor(1).submit(node.nmt.wait_for_bootup, 5)
            time.sleep(0.05)
            node.nmt.state = "RESET COMMUNICATION"
            waiter.result()
            node.sdo["Modes of operation"].raw = objects.MODE_CYCLIC_SYNC_TORQUE
            node.rpdo.read()
            node.rpdo[1].clear()
            node.rpdo[1].add_variable("Controlword")
            node.rpdo[1].add_variable("Target torque")
            node.rpdo[1].trans_type = 255
            node.rpdo[1].enabled = True
            node.rpdo.save()
            node.tpdo.read()
            node.nmt.state = "OPERATIONAL"
            for controlword in (0x06, 0x07, 0x0F):
                node.sdo["Controlword"].raw = controlword
            assert state_from_statusword(node.sdo["Statusword"].raw) is (
                State.OPERATION_ENABLED)
            assert node.sdo["Modes of operation display"].raw == 10
            positions = []
            arrived = threading.Event()  # armed before the SYNC: the TPDO can beat a late wait
            node.tpdo[1].add_callback(lambda _: arrived.set())
            for _ in range(400):
                node.rpdo[1]["Controlword"].raw = 0x0F
                node.rpdo[1]["Target torque"].raw = -300  # -30 % of rated torque: arm goes down
                node.rpdo[1].transmit()
                arrived.clear()
                network.sync.transmit()
                assert arrived.wait(2.0)
                positions.append(node.tpdo[1]["Position actual value"].raw)
            node.sdo["Controlword"].raw = 0x00
    finally:
        network.disconnect()
    assert positions[-1] < positions[0] - 0.2 * objects.INCREMENTS_PER_RAD
    assert np.all(np.diff(positions[50:]) <= 0)
