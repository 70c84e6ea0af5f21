"""The master drives standard CiA 402 drives from their EDS, and the virtual drive behaves like
one for generic masters: python canopen's BaseNode402, a drive with standard objects only, a
drive the loop cannot use, the SYNC counter rules of CiA 301."""

import struct
import subprocess
import sys
import time
from pathlib import Path

import canopen
import numpy as np
import pytest

from driver import ProfileError
from driver.canopen_drive import CanOpenDrive
from driver.clock import DriveClock, WallClock
from model.parameters import Payload, load_model
from protocol import cia301, eds_path, objects
from protocol.cia402 import State
from recorder.reader import load_recording
from sim_bus.embedded import EmbeddedDrive
from sim_bus.plant import SensorNoise
from tests.conftest import (
    can_semantics_network,
    sim_bus_process,
    udp_bus_spec,
    virtual_drive_process,
)

pytestmark = pytest.mark.subprocess  # runs the commands as processes

DATA = Path(__file__).parent / "data"
CST_STANDARD = DATA / "cst_standard.eds"
POSITION_VELOCITY_ONLY = DATA / "position_velocity_only.eds"
MODEL = load_model()


@pytest.mark.real_time
def test_base_node_402_drives_a_fresh_sim_bus_in_cyclic_synchronous_torque():
    """canopen's BaseNode402 as its documentation shows, with SYNC from the master and
    nothing of ours: the joint moves the way the torque says."""
    bus = udp_bus_spec()
    with sim_bus_process(bus):
        network = can_semantics_network(bus)
        try:
            node = canopen.BaseNode402(2, str(eds_path()))
            network.add_node(node)
            node.nmt.state = "RESET COMMUNICATION"
            node.nmt.wait_for_bootup(5)
            node.setup_402_state_machine()
            node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
            node.sdo["Communication cycle period"].raw = 10_000  # us: SYNC at 100 Hz
            network.sync.start(0.01)
            node.nmt.state = "OPERATIONAL"
            node.state = "OPERATION ENABLED"
            assert node.state == "OPERATION ENABLED"
            assert node.op_mode == "CYCLIC SYNCHRONOUS TORQUE"
            start = node.tpdo_values[objects.POSITION_ACTUAL]
            node.sdo["Target torque"].raw = -300  # -30 % of rated torque: the arm goes down
            time.sleep(0.5)
            moved = node.tpdo_values[objects.POSITION_ACTUAL] - start
            node.state = "SWITCH ON DISABLED"
            network.sync.stop()
        finally:
            network.disconnect()
    assert moved < -0.2 * objects.INCREMENTS_PER_RAD


@pytest.mark.real_time
def test_a_standard_cst_drive_in_another_process_is_driven_with_standard_objects_only():
    """Target torque 0x6071 in per mille of 0x6076 through the model's drive gain, current
    actual 0x6078, position and velocity, freshness by the synchronous window: the joint
    follows the commanded current as the model says."""
    bus = udp_bus_spec()
    with virtual_drive_process(bus, 3, "--eds", str(CST_STANDARD)):
        drive = CanOpenDrive.open(bus, 3, velocity_limit=MODEL.limits.velocity_max,
                                  drive_gain=MODEL.parameters.drive_gain, eds=CST_STANDARD,
                                  response_timeout=0.5)
        try:
            assert drive.profile.mode == objects.MODE_CYCLIC_SYNC_TORQUE
            assert not drive.profile.has_joint_torque
            drive.start()
            # the mapping the master wrote reads back from the drive as planned
            assert drive.node.sdo[objects.RPDO_MAP][2].raw == 0x60710010
            assert drive.node.sdo[objects.TPDO_MAP + 1][2].raw == 0x60780010
            assert drive.node.sdo[objects.SYNC_WINDOW_US].raw == 500_000  # response timeout
            samples = []
            for _ in range(300):
                samples.append(drive.sync())
                drive.command_current(-2.0)
        finally:
            drive.close()
    currents = np.array([s.motor_current for s in samples[5:]])
    positions = np.array([s.position for s in samples])
    assert np.median(currents) == pytest.approx(-2.0, abs=0.02)  # 0x6078 per mille of 6 A
    assert positions[-1] < positions[0] - 0.1
    assert np.isnan(samples[-1].joint_torque)  # no torque sensor on a standard drive


def test_a_drive_without_a_torque_mode_is_refused_naming_what_is_missing():
    sim = EmbeddedDrive(MODEL, Payload(), SensorNoise(), 2, clock=WallClock(),
                        eds_path=POSITION_VELOCITY_ONLY)
    frames = []
    sim.network.subscribe(cia301.NMT_COB_ID, lambda *frame: frames.append(frame))
    try:
        with pytest.raises(ProfileError, match=r"cyclic synchronous torque mode \(0x6502 "
                                               r"bit 9\), 0x6071 \(target torque\)"):
            CanOpenDrive(sim.master_network, 2, velocity_limit=MODEL.limits.velocity_max,
                         drive_gain=MODEL.parameters.drive_gain, eds=POSITION_VELOCITY_ONLY)
    finally:
        sim.close()
    assert not frames  # refused from the EDS, before anything reached the drive
    assert sim.device.state is State.SWITCH_ON_DISABLED


def embedded_operational(eds=None) -> tuple[EmbeddedDrive, list[int]]:
    sim = EmbeddedDrive(MODEL, Payload(), SensorNoise(), 2, clock=DriveClock(), eds_path=eds)
    emcys: list[int] = []
    sim.master_network.subscribe(cia301.EMCY_BASE + 2,
                                 lambda _, data, __: emcys.append(struct.unpack("<H",
                                                                                data[:2])[0]))
    sim.master_network.send_message(cia301.NMT_COB_ID, bytes([cia301.NMT_START, 2]))
    return sim, emcys


def test_a_sync_counter_byte_the_drive_does_not_expect_is_an_emcy_8240():
    sim, emcys = embedded_operational()
    try:
        assert sim.device.read(objects.SYNC_COUNTER_OVERFLOW) == 0
        sim.master_network.send_message(cia301.SYNC_COB_ID, b"")
        assert emcys == []
        sim.master_network.send_message(cia301.SYNC_COB_ID, bytes([1]))
        assert emcys == [cia301.EMCY_SYNC_LENGTH]
        sim.master_network.send_message(cia301.SYNC_COB_ID, bytes([2]))
        assert emcys == [cia301.EMCY_SYNC_LENGTH]  # once, not on every SYNC
        # and the other way round: 0x1019 set, a SYNC without its counter
        sim.device.write(objects.SYNC_COUNTER_OVERFLOW, 0, cia301.SYNC_COUNTER_MAX)
        sim.master_network.send_message(cia301.SYNC_COB_ID, bytes([3]))
        sim.master_network.send_message(cia301.SYNC_COB_ID, b"")
        assert emcys == [cia301.EMCY_SYNC_LENGTH, cia301.EMCY_SYNC_LENGTH]
    finally:
        sim.close()


def test_the_default_pdo_mapping_of_the_eds_is_live_at_boot():
    """A generic master that only starts the node gets the EDS's TPDOs on SYNC."""
    sim, _ = embedded_operational(CST_STANDARD)
    got = {}
    for cob_id in (0x182, 0x282):
        sim.master_network.subscribe(cob_id, lambda c, data, _: got.setdefault(c, bytes(data)))
    try:
        sim.master_network.send_message(cia301.SYNC_COB_ID, b"")
    finally:
        sim.close()
    statusword, position = struct.unpack("<Hi", got[0x182])
    assert statusword == 0x0240  # switch on disabled, remote
    assert position == round(sim.device.plant.position * objects.INCREMENTS_PER_RAD)
    assert len(got[0x282]) == 6  # velocity (4) + current actual (2)


def test_a_nmt_reset_leaves_the_power_stage_off_and_the_brake_holds_the_load():
    heavy = Payload(30.0, 0.0, 0.05)  # the paper's heaviest: 25 N.m of gravity at -1.5 rad
    sim = EmbeddedDrive(MODEL, heavy, SensorNoise(), 2, clock=DriveClock(),
                        initial_position=-1.5)
    drive = CanOpenDrive(sim.master_network, 2, velocity_limit=MODEL.limits.velocity_max,
                         clock=DriveClock())
    try:
        drive.start()
        assert sim.device.state is State.OPERATION_ENABLED
        assert not sim.device.brake_engaged
        for command in ("RESET COMMUNICATION", "RESET"):
            drive.enable()
            drive.node.nmt.state = command
            assert sim.device.state is State.SWITCH_ON_DISABLED
            assert sim.device.brake_engaged
        sim.master_network.send_message(cia301.NMT_COB_ID, bytes([cia301.NMT_START, 2]))
        for _ in range(1000):  # a second of SYNCs from anyone: the brake holds the joint
            sim.master_network.send_message(cia301.SYNC_COB_ID, b"")
        assert sim.device.plant.position == pytest.approx(-1.5, abs=1e-3)
    finally:
        drive.close()
        sim.close()


def test_a_fresh_drive_has_its_physics_compiled_before_it_boots():
    """Nothing is compiled on the bus path (a fresh sim-bus answered its first SYNC 0.3-0.5 s
    late): building the device compiles, or loads, the integrator. The cycle's integrator is
    the compiled period of `sim_bus.sensing` (physics and sensors in one call), the sample at
    a reset its `sample`."""
    probe = ("from sim_bus import sensing; from model.parameters import load_model; "
             "from sim_bus.device import Cia402Device; "
             "kernels = (sensing.advance_and_sample, sensing.sample); "
             "assert not any(k.signatures for k in kernels); Cia402Device(load_model()); "
             "print(*(len(k.signatures) for k in kernels))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1", "1"]


@pytest.mark.real_time
def test_without_an_echo_a_tpdo_from_before_the_sync_is_not_taken_for_its_answer():
    """A standard drive does not echo the SYNC counter: the synchronous window decides. A
    frame stamped before SYNC k (a late answer to k-1 crossing it) is refused."""
    sim = EmbeddedDrive(MODEL, Payload(), SensorNoise(), 2, clock=WallClock(),
                        eds_path=CST_STANDARD)
    drive = CanOpenDrive(sim.master_network, 2, velocity_limit=MODEL.limits.velocity_max,
                         drive_gain=MODEL.parameters.drive_gain, eds=CST_STANDARD)
    stale = struct.pack("<Hi", 0x0237, 12345)

    def cross(can_id, data, timestamp):  # reaches the master just ahead of the real answer
        drive.network.notify(0x182, stale, time.time() - 0.01)

    try:
        drive.start()
        sim.network.subscribers[cia301.SYNC_COB_ID].insert(0, cross)
        sample = drive.sync()
    finally:
        drive.close()
        sim.close()
    assert objects.position_to_increments(sample.position) != 12345
    assert any("outside the 100 ms synchronous window" in w for w in drive.warnings())


@pytest.mark.real_time
def test_actuatord_and_recorder_drive_a_standard_cst_sim_bus_from_its_eds(tmp_path):
    """The commands as a user runs them on a drive with standard objects only: `sim-bus --eds`
    serves it, `actuatord --eds` and `recorder --eds` drive it in cyclic synchronous torque."""
    bus = udp_bus_spec()
    eds = ["--eds", str(CST_STANDARD)]
    with sim_bus_process(bus, "--node-id", "3", *eds):
        controlled = subprocess.run(
            [sys.executable, "-m", "commands.actuatord", "--bus", bus, "--node-id", "3", *eds,
             "--duration", "2", "--no-multicast-scouting"],
            capture_output=True, text=True, timeout=120)
        assert controlled.returncode == 0, controlled.stderr
        assert "2000 cycles" in controlled.stdout
        recording = tmp_path / "sinusoid.mcap"
        recorded = subprocess.run(
            [sys.executable, "-m", "commands.recorder", "--bus", bus, "--node-id", "3", *eds,
             "--sinusoid", "--duration", "2", "--no-progress", "-o", str(recording)],
            capture_output=True, text=True, timeout=120)
        assert recorded.returncode == 0, recorded.stderr
    samples = load_recording(recording)
    assert len(samples) >= 1900
    assert np.ptp(samples.q) > 0.05  # the slow sinusoid moved the joint
    assert np.all(np.isnan(samples.joint_torque))  # a standard drive has no torque sensor
    # identification needs the sensor: one line, exit 2, no model written
    identified = subprocess.run(
        [sys.executable, "-m", "commands.identify", str(recording), str(recording),
         "--payload-mass", "0", "-o", str(tmp_path / "m.toml")],
        capture_output=True, text=True, timeout=60)
    assert identified.returncode == 2
    assert identified.stderr.count("\n") == 1 and "no joint-torque readings" in (
        identified.stderr)
    assert not (tmp_path / "m.toml").exists()


@pytest.mark.parametrize("command", ["actuatord", "recorder"])
def test_the_commands_refuse_a_drive_without_a_torque_mode_before_touching_it(command,
                                                                               tmp_path):
    """Refused from the EDS alone, before a bus is opened (none is given here: with --sim the
    embedded drive would serve the same EDS)."""
    extra = (["--no-multicast-scouting"] if command == "actuatord"
             else ["--exciting-trajectory", "-o", str(tmp_path / "x.mcap")])
    result = subprocess.run(
        [sys.executable, "-m", f"commands.{command}", "--sim", "--eds",
         str(POSITION_VELOCITY_ONLY), *extra], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "0x6071" in lines[0] and "torque mode" in lines[0]
    assert not (tmp_path / "x.mcap").exists()


def test_a_model_asking_more_current_than_the_drive_accepts_is_refused_before_enabling(
        tmp_path):
    """The drive's limit is its own (0x6073 x 0x6075, read at start): a model whose
    current_max is above it is refused before the power stage is on, not at its first big
    command."""
    text = eds_path().parent.parent.joinpath("model", "elbow_default.toml").read_text()
    lines = text.splitlines()
    first = next(k for k, line in enumerate(lines) if line.startswith("current_max ="))
    lines[first] = "current_max = 100.0"
    greedy = tmp_path / "greedy.toml"
    greedy.write_text("\n".join(lines) + "\n")
    result = subprocess.run(
        [sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep", "--duration", "1",
         "--model", str(greedy), "--no-multicast-scouting"],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "current_max 100 A" in lines[0], result.stderr
    assert "enabled" not in result.stdout
