"""Master + virtual drive in one process (linked as `--sim` links them), in lock-step."""

import math
import time

import numpy as np
import pytest

from driver import CommandRangeError, DriveFault, DriveLost, DriveTimeout
from model import dynamics
from model.dynamics import SUBSTEPS
from model.parameters import Payload
from protocol import cia301, cia402, objects
from protocol import pdo as pdo_layout
from protocol.cia402 import State
from tests.conftest import virtual_pair, wait_for

HALF_COUNT = 0.5 / objects.INCREMENTS_PER_RAD  # encoder quantisation bound (rad)


def current_profile(n: int) -> np.ndarray:
    """Steps and a chirp-like swing well inside the position window and the 6 A limit."""
    t = np.arange(n) * 1e-3
    return -1.2 + 0.6 * np.sin(2 * math.pi * 0.7 * t) + 0.3 * np.sign(np.sin(2 * math.pi * 2 * t))


def run_profile(sim, master, currents):
    samples = []
    for current in currents:
        samples.append(master.sync())
        master.command_current(float(current))
    return samples


def test_boot_enable_and_motion_match_the_model(pair):
    sim, master = pair
    q0 = sim.device.plant.position
    master.start()
    assert sim.device.state is State.OPERATION_ENABLED
    currents = current_profile(3000)
    samples = run_profile(sim, master, currents)
    # sample k+1 results from the command sent after sample k (the first cycle runs at 0 A);
    # the RPDO carries whole milliamps
    applied = np.round(np.concatenate(([0.0], currents[:-1])) * 1000) / 1000
    expected = dynamics.simulate(q0, 0.0, applied, sim.device.plant.parameters.packed(), 1e-3,
                                 SUBSTEPS)
    measured = np.array([s.position for s in samples])
    # the physics is the model's own integrator: only the 19-bit quantisation separates them
    assert np.max(np.abs(measured - expected[:, 0])) <= HALF_COUNT + 1e-12
    assert np.ptp(measured) > 0.3  # it really moved
    assert samples[-1].t == pytest.approx(3.0)
    measured_current = np.array([s.motor_current for s in samples])
    # 10 mA current-sensor noise (seeded): the mean error is far below one noise std
    assert abs(np.mean(measured_current - applied)) < 0.003
    assert cia402.state_from_statusword(samples[-1].statusword) is State.OPERATION_ENABLED


def test_same_seed_gives_the_same_run():
    runs = []
    for _ in range(2):
        with virtual_pair() as (sim, master):
            master.start()
            runs.append([(s.position, s.motor_current, s.joint_torque)
                         for s in run_profile(sim, master, current_profile(300))])
    assert runs[0] == runs[1]


def test_payload_changes_the_hanging_torque():
    with virtual_pair(payload=Payload(10.0, 0.0, 0.05)) as (sim, master):
        master.start()
        hold = -1.0
        for _ in range(50):
            sample = master.sync()
            master.command_current(hold)
        assert sim.device.plant.parameters.first_moment_y == pytest.approx(1.1 + 0.5)
        assert sample.joint_torque < -1.0


def test_out_of_range_command_is_refused_and_nothing_sent(pair):
    sim, master = pair
    master.start()
    master.sync()
    master.command_current(1.0)
    with pytest.raises(CommandRangeError, match=r"7.000 A outside the drive's limit of \+/-6.000"):
        master.command_current(7.0)
    with pytest.raises(CommandRangeError, match="not a finite number"):
        master.command_current(float("nan"))
    master.sync()
    assert sim.device.applied_current == pytest.approx(1.0)


def test_close_leaves_the_drive_disabled(pair):
    sim, master = pair
    master.start()
    master.sync()
    master.command_current(2.0)
    master.sync()
    master.close()
    time.sleep(0.05)
    assert sim.device.state is State.SWITCH_ON_DISABLED
    assert sim.nmt_state_name == "PRE-OPERATIONAL"


@pytest.mark.real_time
def test_heartbeat_loss_is_reported_within_three_periods_and_commanding_stops():
    """Real time: the consumer runs on the clock while no cycle runs."""
    with virtual_pair(lockstep=False) as (sim, master):
        _heartbeat_loss_is_reported(sim, master)


def _heartbeat_loss_is_reported(sim, master):
    master.start()
    master.sync()
    sim.stop_heartbeat()
    stopped = time.monotonic()
    deadline = stopped + 1.0
    while not isinstance(master.fault, DriveLost) and time.monotonic() < deadline:
        time.sleep(0.002)
    detected = time.monotonic()
    assert isinstance(master.fault, DriveLost)
    period = master.transport.health.heartbeat_ms / 1000
    # counted from the last heartbeat the drive sent, as a heartbeat consumer does
    assert detected - master.transport.health.last_heartbeat <= 3 * period
    with pytest.raises(DriveLost, match="heartbeat missing"):
        master.command_current(0.5)
    with pytest.raises(DriveLost):
        master.sync()


def test_silent_drive_times_out_the_sync():
    with virtual_pair(response_timeout=0.05) as (sim, master):
        master.start()
        master.sync()
        sim.go_silent()
        with pytest.raises(DriveTimeout, match="no TPDO 0x182, 0x282, 0x382 within 50 ms"):
            master.sync()


def send_raw_command(master, controlword, milliamps):
    payload = pdo_layout.encode(pdo_layout.RPDO_COMMAND, {
        objects.CONTROLWORD: controlword, objects.TARGET_CURRENT: milliamps})
    master.network.send_message(pdo_layout.RPDO_COMMAND.cob_id(master.node_id), payload)


def test_overcurrent_trips_with_emcy_and_reset_recovers(pair):
    sim, master = pair
    master.start()
    master.sync()
    send_raw_command(master, 0x0F, 9000)  # past the 8 A trip level, bypassing our checks
    sample = master.sync()
    assert cia402.state_from_statusword(sample.statusword) is State.FAULT
    assert wait_for(lambda: master.last_emergency is not None, 1.0)
    assert master.last_emergency.code == cia301.EMCY_OVERCURRENT
    assert isinstance(master.fault, DriveFault)
    assert sim.device.applied_current == 0.0
    with pytest.raises(DriveFault, match="EMCY 0x2310"):
        master.command_current(0.1)
    master.fault_reset()
    assert master.state() is State.SWITCH_ON_DISABLED
    master.enable()
    master.command_current(0.5)
    sample = master.sync()
    assert cia402.state_from_statusword(sample.statusword) is State.OPERATION_ENABLED
    assert sim.device.applied_current == pytest.approx(0.5)


def test_current_is_saturated_at_max_current_like_a_real_drive(pair):
    sim, master = pair
    master.start()
    master.sync()
    send_raw_command(master, 0x0F, 7000)  # above max current, below the trip level
    master.sync()
    assert sim.device.applied_current == pytest.approx(6.0)


def test_position_limit_fault_sends_emcy(pair):
    sim, master = pair
    master.start()
    for _ in range(3000):
        sample = master.sync()
        if cia402.state_from_statusword(sample.statusword) is State.FAULT:
            break
        master.command_current(-3.0)  # drives the arm down through -2.45 rad
    assert cia402.state_from_statusword(sample.statusword) is State.FAULT
    assert sample.position < -2.44
    assert wait_for(lambda: master.last_emergency is not None, 1.0)
    assert master.last_emergency.code == cia301.EMCY_POSITION_LIMIT
