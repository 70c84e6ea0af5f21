"""Opening a robot's drives: the wiring of its lines and drives, real or virtual.

One joint or a robot file's joints, each drive on its CAN bus (python-can + canopen) or its
EtherCAT line (pysoem), or with `--sim` a virtual drive (`sim_bus`) linked to the master in
this process. This is the composition root: the one place a master meets a virtual drive, so
tests and programs build a robot without the command line. Every failure to open is a
DriveOpenError naming the bus (the command turns it into exit code 1); the typed values come
checked from the caller (the command layer parses and checks options).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import can

from driver.clock import Clock
from model.parameters import ActuatorModel, Payload
from protocol.bus_spec import is_ethercat, parse_bus_spec
from robot.can_log import CanLog, LoggedBus, tap_link

if TYPE_CHECKING:  # imported when a drive is opened: describing a bus needs none of them
    import canopen

    from driver.cia402_drive import Cia402Drive
    from driver.drive_group import DriveGroup
    from protocol.esi import EsiDevice
    from robot.description import JointSpec, RobotSpec
    from sim_bus.device import Cia402Device
    from sim_bus.embedded import EmbeddedBus
    from sim_bus.faults import Fault


def describe_bus(config: dict) -> str:
    """A python-can configuration as the user reads it: `interface:channel`."""
    channel = config.get("channel")
    return f"{config['interface']}:{channel}" if channel is not None else config["interface"]


def open_can_network(config: dict, can_log: CanLog | None = None) -> canopen.Network:
    """A connected canopen Network on the bus python-can's `config` names; `can_log` gets
    every frame. Raises what python-can raises."""
    import canopen

    from driver.canopen_transport import NOTIFIER_CYCLE

    if config["interface"] == "udp_multicast" and can_log is None:
        from driver.canopen_multicast import MulticastNetwork

        return MulticastNetwork(config)
    # the lean udp_multicast path has no bus object to log through: with --can-log a frame
    # goes python-can's way (LoggedBus), slower but every frame logged, echoes once

    bus = can.Bus(ignore_config=True, **config)
    if can_log is not None:
        bus = LoggedBus(bus, can_log)
    network = canopen.Network(bus)
    network.NOTIFIER_CYCLE = NOTIFIER_CYCLE
    try:
        network.connect()
    except Exception:
        bus.shutdown()
        raise
    return network


class DriveOpenError(Exception):
    """The bus or the drive could not be opened (the job fails: exit code 1)."""


@dataclass
class Connection:
    """A robot's drives as one group (one joint: a robot of one, named by the caller) and what
    was opened for them: the embedded virtual buses (`--sim`), the virtual drives by joint
    (`--sim`), the CAN log (`--can-log`). Closed together in that order: the drives first, so
    every one is disabled while its bus still carries it."""

    group: DriveGroup
    sim: list[EmbeddedBus] = field(default_factory=list)
    devices: dict[str, Cia402Device] = field(default_factory=dict)  # joint -> virtual drive
    can_log: CanLog | None = None
    where: str = ""  # the bus, as the user reads it (one joint)
    address: str = ""  # the drive on it, as the user reads it: "node 2", "slave 0"

    def close(self) -> None:
        try:
            self.group.close()
        finally:
            try:
                for bus in self.sim:
                    bus.close()
            finally:
                if self.can_log is not None:
                    self.can_log.stop()


def _one(drive: Cia402Drive, name: str, **parts) -> Connection:
    """A single drive as a robot of one joint named `name`."""
    from driver.drive_group import single_joint

    return Connection(single_joint(drive, name), **parts)


def _master_options(model: ActuatorModel, clock: Clock, timing: dict) -> dict:
    """What the master knows of the joint (`model`: its velocity limit guards the encoder, its
    drive gain converts torque commands, its current limit caps the drive), its timing
    (`period`, `response_timeout`) and the clock of its bus (the run's `clock`'s `for_bus`:
    drive time of the bus's own in lock-step)."""
    return {"clock": clock.for_bus(), "velocity_limit": model.limits.velocity_max,
            "drive_gain": model.parameters.drive_gain,
            "current_max": model.limits.current_max, **timing}


def open_line_drive(bus: str, slave: int, model: ActuatorModel, *, esi: EsiDevice | None,
                    eds: str | None, clock: Clock, name: str = "joint",
                    **timing) -> Connection:
    """The master drive of the slave at 0-based position `slave` on the EtherCAT line `bus`
    (`ethercat:IFACE`), read through `esi` (None: the shipped ESI) and `eds`. Call after every
    option is checked: this is where the line is touched. Raises DriveOpenError (exit 1)."""
    from driver.ethercat_drive import JointOnLine

    options = _master_options(model, clock, timing)
    joint = JointOnLine(slave, options.pop("velocity_limit"), options.pop("drive_gain"),
                        current_max=options.pop("current_max"))
    drive = _open_on_line(bus, parse_bus_spec(bus)["channel"], [joint], esi=esi, eds=eds,
                          **options)[0]
    return _one(drive, name, where=bus, address=f"slave {slave}")


def open_can_drive(config: dict, node_id: int, model: ActuatorModel, *, eds: str | None,
                   clock: Clock, can_log: CanLog | None = None, name: str = "joint",
                   **timing) -> Connection:
    """The master drive at `node_id` on the CAN bus python-can's `config` names, every frame
    logged to `can_log` (which the connection then owns: it is stopped with it, or at once if
    the drive cannot be opened). Raises DriveOpenError (exit 1)."""
    from driver.canopen_drive import CanOpenDrive

    options = _master_options(model, clock, timing)
    where = describe_bus(config)
    try:
        network = open_can_network(config, can_log)
    except Exception as exc:
        if can_log is not None:
            can_log.stop()
        raise DriveOpenError(f"cannot open bus {where}: {exc}") from exc
    try:
        return _one(CanOpenDrive(network, node_id, eds=eds, **options), name,
                    can_log=can_log, where=where, address=f"node {node_id}")
    except Exception as exc:
        network.disconnect()
        if can_log is not None:
            can_log.stop()
        raise DriveOpenError(f"cannot use bus {where}: {exc}") from exc


def open_embedded_drive(model: ActuatorModel, sim_model: ActuatorModel, payload: Payload,
                        node_id: int, *, seed: int, eds: str | None,
                        schedule: Iterable[tuple[Fault, float]] = (),
                        clock: Clock, can_log: CanLog | None = None, name: str = "joint",
                        **timing) -> Connection:
    """`--sim`: a virtual drive in this process, `sim_model` and `payload` its physics (its
    hidden truth), `schedule` its injected faults, its noise seeded `seed`, linked to a master
    that knows `model`; the link's frames logged to `can_log` (owned as by `open_can_drive`).
    Raises DriveOpenError (exit 1)."""
    from driver.canopen_drive import CanOpenDrive
    from sim_bus.embedded import EmbeddedDrive
    from sim_bus.plant import SensorNoise

    options = _master_options(model, clock, timing)
    sim = EmbeddedDrive(sim_model, payload, SensorNoise(seed=seed), node_id,
                        clock=clock.for_bus(), eds_path=eds)
    if can_log is not None:
        tap_link(sim.master_network, sim.network, can_log,
                 None if clock.runs_alone else (lambda: sim.device.period))
    for fault, seconds in schedule:
        sim.device.schedule(fault, seconds)
    try:
        return _one(CanOpenDrive(sim.master_network, node_id, eds=eds, **options), name,
                    sim=[sim], devices={name: sim.device}, can_log=can_log, where="--sim",
                    address=f"node {node_id}")
    except Exception as exc:
        sim.close()
        if can_log is not None:
            can_log.stop()
        raise DriveOpenError(f"cannot open the embedded drive: {exc}") from exc


def _open_on_line(bus: str, interface: str, joints: list, **options) -> list[Cia402Drive]:
    """The drives of `joints` (driver.ethercat_drive.JointOnLine) on the EtherCAT line at
    `interface`, the line scanned: the interface opened, every slave's identity checked
    against the ESI, each joint's slave found, the line in PRE-OP. So a missing interface, no
    raw socket, a line that does not answer or a position past its end fails here, naming the
    bus, before the controller is built; the drives start (and the line goes to OP) later.
    `options` go to `open_ethercat_drives`. Raises DriveOpenError (exit code 1)."""
    from driver.cia402_drive import BOOT_TIMEOUT
    from driver.ethercat_drive import open_ethercat_drives

    try:
        drives = open_ethercat_drives(interface, joints, **options)
    except Exception as exc:  # ProfileError, EsiError, OSError: the line was not touched
        raise DriveOpenError(f"cannot use bus {bus}: {exc}") from exc
    try:
        for drive in drives:
            drive.transport.boot(BOOT_TIMEOUT)  # the first scans the line for all of them
    except Exception as exc:
        for drive in drives:
            drive.close()  # not started: only the line is released
        raise DriveOpenError(f"cannot open bus {bus}: {exc}") from exc
    return drives


# --- a robot: every joint's drive, on its bus or embedded ---------------------------------------

def open_robot(robot: RobotSpec, *, sim: bool, clock: Clock, seed: int, period: float,
               response_timeout: float | None = None,
               faults: Iterable[tuple[str, Fault, float]] = ()) -> Connection:
    """Every joint's drive, grouped by bus: one SYNC per CAN bus and one frame per EtherCAT
    line a cycle (`driver.drive_group`; a line's joints opened in slave order, the group
    keeps the file's joint order). With `sim`, every bus keeps its kind, one virtual drive
    per joint, commissioned for the joint's model (`sim_bus.commissioning`), its physics the
    joint's model, its noise seeded `seed` + the joint's index: a CAN bus is an in-process
    CANopen link, an EtherCAT line a line of virtual slaves linked to the master's process
    image in this process (`sim_bus.ethercat.linked`: the same PDO layout, state machine and
    CoE objects as on a wire, one image a cycle). Each bus and line runs on a clock of its
    own from the run's `clock` (`for_bus`); `response_timeout` (s, default: the clock's)
    bounds the wait for a drive's answer. Raises DriveOpenError (exit 1)."""
    from driver.canopen_transport import CanOpenTransport, open_network
    from driver.cia402_drive import Cia402Drive
    from driver.drive_group import CanOpenBus, DriveGroup, EthercatLine
    from driver.ethercat_drive import JointOnLine

    faults = list(faults)
    segments, embedded, devices = [], [], {}
    try:
        for bus, joints in robot.buses().items():
            if is_ethercat(bus):
                on_line = sorted(joints, key=lambda joint: joint.address)
                options = {}
                if sim:  # the line's slaves in this process, linked to the master's image
                    options["open_master"] = _linked_line(
                        robot, on_line, seed, faults, devices, clock)
                segments.append(EthercatLine(bus, []))
                drives = _open_on_line(bus, parse_bus_spec(bus)["channel"], [
                    JointOnLine(j.address, j.model.limits.velocity_max,
                                j.model.parameters.drive_gain, j.eds,
                                j.model.limits.current_max, j.name, j.startup)
                    for j in on_line],
                    period=period, clock=clock.for_bus(), response_timeout=response_timeout,
                    sync=robot.sync(bus), **options)
                segments[-1].joints = [(j.name, drive)
                                       for j, drive in zip(on_line, drives, strict=True)]
                continue
            addresses = {j.name: j.address for j in joints}
            if sim:
                from sim_bus.embedded import EmbeddedBus
                from sim_bus.plant import SensorNoise

                link = EmbeddedBus(clock=clock.for_bus())
                embedded.append(link)
                for joint in joints:
                    index = robot.joints.index(joint)
                    devices[joint.name] = device = link.add_drive(
                        joint.model, Payload(), SensorNoise(seed=seed + index),
                        addresses[joint.name], eds_path=joint.eds, commissioned=True)
                    for name, fault, seconds in faults:
                        if name == joint.name:
                            device.schedule(fault, seconds)
                network = link.master_network
            else:
                network = open_network(bus, robot.bitrates.get(bus))
            segments.append(CanOpenBus(bus, network, []))
            bus_clock = clock.for_bus()
            for joint in joints:
                transport = CanOpenTransport(network, addresses[joint.name], eds=joint.eds,
                                             clock=bus_clock,
                                             response_timeout=response_timeout,
                                             owns_network=False)
                segments[-1].joints.append((joint.name, Cia402Drive(
                    transport, velocity_limit=joint.model.limits.velocity_max, period=period,
                    drive_gain=joint.model.parameters.drive_gain,
                    current_max=joint.model.limits.current_max, startup=joint.startup)))
        return Connection(DriveGroup([j.name for j in robot.joints], segments), embedded,
                          devices)
    except Exception as exc:
        for segment in segments:
            for _, drive in segment.joints:
                drive.transport.close()
            segment.close()
        for link in embedded:
            link.close()
        if isinstance(exc, DriveOpenError):
            raise DriveOpenError(f"{robot.source}: {exc}") from exc
        raise DriveOpenError(f"cannot open the drives of {robot.source}: {exc}") from exc


def _linked_line(robot: RobotSpec, on_line: list, seed: int,
                 faults: list[tuple[str, Fault, float]],
                 devices: dict[str, Cia402Device], clock: Clock) -> Callable[[], object]:
    """`--sim` for an EtherCAT line: a virtual drive per joint (commissioned for its model,
    its noise seeded `seed` + the joint's index, its scheduled faults), in slave order, as a
    line of slaves in this process; what makes the master that drives them
    (`sim_bus.ethercat.linked`). The drives go into `devices` by joint name."""
    from sim_bus.embedded import make_device
    from sim_bus.ethercat.linked import LinkedMaster
    from sim_bus.ethercat.segment import Segment as VirtualLine
    from sim_bus.plant import SensorNoise

    line = []
    for joint in on_line:
        device = make_device(joint.model, Payload(),
                             SensorNoise(seed=seed + robot.joints.index(joint)),
                             eds_path=joint.eds, commissioned=True)
        for name, fault, seconds in faults:
            if name == joint.name:
                device.schedule(fault, seconds)
        devices[joint.name] = device
        line.append(device)
    segment = VirtualLine(line)
    return lambda: LinkedMaster(segment, clock.for_bus())


def open_joint(robot: RobotSpec, joint: JointSpec, sim_model: ActuatorModel,
               payload: Payload, *, sim: bool, clock: Clock, seed: int,
               **timing) -> Connection:
    """One joint of a robot file alone, the others not started (their drives stay as they
    powered up: switch on disabled, brake engaged; on an EtherCAT line they follow it to OP,
    with a zero controlword): its drive on its bus at its node id or slave position, or with
    `sim` a virtual drive commissioned for it on an in-process CANopen link (an EtherCAT
    joint's too, see `open_robot`), its physics `sim_model`. Raises DriveOpenError (exit
    1)."""
    from driver.canopen_drive import CanOpenDrive

    timing = {"clock": clock.for_bus(), "velocity_limit": joint.model.limits.velocity_max,
              "drive_gain": joint.model.parameters.drive_gain, "eds": joint.eds,
              "current_max": joint.model.limits.current_max, "startup": joint.startup,
              **timing}
    kind = "slave" if joint.on_ethercat else "node"
    if not sim and joint.on_ethercat:
        from driver.ethercat_drive import JointOnLine

        on_line = JointOnLine(joint.address, timing.pop("velocity_limit"),
                              timing.pop("drive_gain"), timing.pop("eds"),
                              timing.pop("current_max"), joint.name, timing.pop("startup"))
        drive = _open_on_line(joint.bus, parse_bus_spec(joint.bus)["channel"], [on_line],
                              **timing)[0]
        return _one(drive, joint.name, where=joint.bus, address=f"slave {joint.address}")
    if not sim:
        try:
            return _one(CanOpenDrive.open(joint.bus, joint.address, **timing), joint.name,
                        where=joint.bus, address=f"node {joint.address}")
        except Exception as exc:
            raise DriveOpenError(f"cannot use bus {joint.bus}: {exc}") from exc
    from sim_bus.embedded import EmbeddedBus
    from sim_bus.plant import SensorNoise

    node_id = 1 if joint.on_ethercat else joint.address
    link = EmbeddedBus(clock=clock.for_bus())
    try:
        device = link.add_drive(sim_model, payload, SensorNoise(seed=seed), node_id,
                                eds_path=joint.eds, commissioned=True)
        return _one(CanOpenDrive(link.master_network, node_id, **timing), joint.name,
                    sim=[link], devices={joint.name: device}, where="--sim",
                    address=f"{kind} {joint.address}")
    except Exception as exc:
        link.close()
        raise DriveOpenError(f"cannot open the embedded drive of {joint.name}: {exc}") from exc
