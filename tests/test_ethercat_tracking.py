"""Over EtherCAT the loop works as over CAN: the same controller, model and reference for 5 s
of drive time in lock-step track alike, and the exciting trajectory recorded over both
identifies the same model. Once on the embedded CANopen drive (`--sim`, current mode) and once
on a virtual EtherCAT slave over the veth (cyclic synchronous torque, per mille units)."""

import numpy as np
import pytest

from commands.identify import main as identify
from controller import messages
from controller.loop import ControlLoop, LoopOptions
from controller.mpc import Mpc
from controller.problem import OcpSettings
from controller.reference import Sinusoid
from driver.canopen_drive import CanOpenDrive
from driver.clock import DriveClock, clock_for
from driver.drive_group import single_joint
from driver.ethercat_drive import JointOnLine, open_ethercat_drive
from model.parameters import Payload, load_model
from recorder.csv_io import write_csv
from recorder.exciting import ExcitingTrajectory
from recorder.experiment import run_trajectory
from recorder.recording import Recording
from recorder.tracking import TrackingLaw
from sim_bus.embedded import EmbeddedDrive
from sim_bus.ethercat.netns import SlaveProcess, VirtualLink
from sim_bus.plant import SensorNoise

MODEL = load_model()
DURATION = 5.0  # s of drive time


def track(drive) -> tuple[int, float, int]:
    """(exit code, tracking RMS in rad, cycles) of the MPC on `drive` for DURATION."""
    mpc = Mpc(MODEL, OcpSettings(), Payload(), Sinusoid())
    loop = ControlLoop(single_joint(drive), mpc,
                       LoopOptions(period=1e-3, clock=DriveClock(), duration=DURATION,
                                   keep_history=True))
    try:
        drive.start()
        report = loop.run()
    finally:
        drive.close()
    history = report.history
    error = np.asarray(history["position"]) - np.asarray(history["reference"])
    return report.exit_code, float(np.sqrt(np.mean(error ** 2))), report.cycles


def can_drive(sim: EmbeddedDrive) -> CanOpenDrive:
    return CanOpenDrive(sim.master_network, 2, velocity_limit=MODEL.limits.velocity_max,
                        drive_gain=MODEL.parameters.drive_gain, clock=DriveClock())


def ethercat_drive(link: VirtualLink):
    return open_ethercat_drive(link.master_port, JointOnLine(
        0, MODEL.limits.velocity_max, MODEL.parameters.drive_gain), clock=clock_for(True))


@pytest.mark.real_time
def test_mpc_over_ethercat_tracks_within_ten_percent_of_can(link):
    sim = EmbeddedDrive(MODEL, Payload(), SensorNoise(seed=0), 2, clock=DriveClock())
    try:
        can_code, can_rms, can_cycles = track(can_drive(sim))
    finally:
        sim.close()
    with SlaveProcess(link, 1, MODEL), link.entered():
        code, rms, cycles = track(ethercat_drive(link))
    assert (can_code, code) == (0, 0)
    assert cycles == can_cycles == round(DURATION / 1e-3)
    assert rms == pytest.approx(can_rms, rel=0.10), (rms, can_rms)


LOAD = Payload(5.0, 0.0, 0.1)
SHORT = ExcitingTrajectory(velocity_min=0.8, steps=3)  # 15 s, as the identification tests


def record(drive, payload: Payload, path) -> None:
    """The exciting trajectory with its tracking law, written as the CSV interchange file."""
    columns = {"t": [], "q": [], "current": [], "joint_torque": []}

    def sink(message) -> None:
        if type(message) is messages.State:
            for key, value in (("t", message.t), ("q", message.position),
                               ("current", message.motor_current),
                               ("joint_torque", message.joint_torque)):
                columns[key].append(value)

    law = TrackingLaw(MODEL.parameters.with_payload(payload), MODEL.limits.current_max)
    try:
        drive.start()
        report = run_trajectory(single_joint(drive), SHORT, law, MODEL.limits, [sink],
                                clock=DriveClock())
        assert report.exit_code == 0, report.reason
    finally:
        drive.close()
    write_csv(Recording(**{k: np.asarray(v) for k, v in columns.items()}, metadata={
        "payload_mass": str(payload.mass), "payload_position": f"{payload.x},{payload.y}"}),
        path)


@pytest.mark.real_time
def test_exciting_trajectory_over_ethercat_identifies_the_model_as_over_can(link, tmp_path):
    models = {}
    for bus in ("can", "ethercat"):
        files = []
        for name, payload in (("noload", Payload()), ("load", LOAD)):
            path = tmp_path / f"{bus}-{name}.csv"
            if bus == "can":
                sim = EmbeddedDrive(MODEL, payload, SensorNoise(seed=len(files)), 2,
                                    clock=DriveClock())
                try:
                    record(can_drive(sim), payload, path)
                finally:
                    sim.close()
            else:
                with SlaveProcess(link, 1, MODEL, payload, SensorNoise(seed=len(files))), \
                        link.entered():
                    record(ethercat_drive(link), payload, path)
            files.append(str(path))
        models[bus] = tmp_path / f"{bus}.toml"
        assert identify([*files, "-o", str(models[bus])]) == 0
    can, ethercat = (load_model(models[bus]).parameters for bus in ("can", "ethercat"))
    for name in ("drive_gain", "torque_sensor_gain", "first_moment_x", "first_moment_y",
                 "link_inertia", "motor_inertia", "viscous_friction_motor",
                 "viscous_friction_joint", "dry_friction_motor", "dry_friction_joint"):
        assert getattr(ethercat, name) == pytest.approx(getattr(can, name), rel=0.03,
                                                        abs=1e-4), name
