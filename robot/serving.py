"""A robot's drives served as virtual drives on its real buses (`sim-bus --robot`): each CAN
joint a CANopen node on its bus at its node id, each EtherCAT line its joints as slaves in
slave order on its interface, every drive commissioned for its joint's model. The other half
of the wiring in `robot.wiring` (which puts masters on those buses), so a test or a program
serves a robot without the command line."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass, field

from model.parameters import Payload
from protocol.bus_spec import is_ethercat, parse_bus_spec
from robot.description import JointSpec, RobotSpec
from sim_bus.device import Cia402Device
from sim_bus.plant import SensorNoise


class LineThread(threading.Thread):
    """One EtherCAT line of virtual slaves answering on its interface until `stop`."""

    def __init__(self, bus: str, interface: str, devices: Sequence[Cia402Device],
                 stop: threading.Event) -> None:
        super().__init__(daemon=True, name=f"line-{interface}")
        self.bus, self.interface, self.devices, self.stop = bus, interface, devices, stop
        self.ready = threading.Event()
        self.failure: Exception | None = None

    def run(self) -> None:
        from sim_bus.ethercat.segment import serve

        try:
            serve(self.interface, self.devices, self.stop, on_ready=lambda _: self.ready.set())
        except Exception as exc:  # OSError: no such interface, no raw socket
            self.failure = exc
        finally:
            self.ready.set()

    def wait_ready(self) -> None:
        """Return once the line answers; raise why it cannot."""
        self.ready.wait()
        if self.failure is not None:
            raise OSError(f"bus {self.bus}: {self.failure}")


@dataclass
class ServedRobot:
    """The served drives, bus by bus: `served` pairs each joint with its virtual drive.
    `stop` ends the EtherCAT lines; `close` also releases the CAN nodes and buses."""

    served: list[tuple[str, Cia402Device]] = field(default_factory=list)
    stop: threading.Event = field(default_factory=threading.Event)
    lines: list[LineThread] = field(default_factory=list)
    nodes: list = field(default_factory=list)  # sim_bus.canopen_node.CanOpenNode
    networks: list = field(default_factory=list)  # canopen.Network, one per CAN bus
    receiver: threading.Thread | None = None  # sim_bus.multicast's, for the udp_multicast buses

    def failed_line(self) -> LineThread | None:
        """The first EtherCAT line that stopped answering, if any."""
        return next((line for line in self.lines if line.failure), None)

    def serve_until(self, stop: threading.Event) -> None:
        """Answer until `stop` is set or a line fails; then stop every line."""
        while not stop.is_set() and self.failed_line() is None:
            stop.wait(0.1)
        self.stop.set()
        for line in self.lines:
            line.join()

    def close(self) -> None:
        """Stop the lines, then release the CAN nodes and buses. Idempotent."""
        self.stop.set()
        for line in self.lines:
            if line.ident is not None:  # started
                line.join()
        if self.receiver is not None:
            self.receiver.stop()
        for node in self.nodes:
            node.close()
        for network in self.networks:
            network.disconnect()


def serve_robot(robot: RobotSpec, *, seed: int, current_noise: float, torque_noise: float,
                silence_timeout: float | None) -> ServedRobot:
    """Every drive of `robot` on its bus, answering once this returns: noise seeded `seed` +
    the joint's index, a CAN drive's master-silence time `silence_timeout` (None: off). Raises
    what python-can or the raw socket raises (CanError, OSError, ImportError), with whatever
    was opened released."""
    from driver.canopen_transport import open_network
    from driver.clock import WallClock
    from sim_bus.embedded import make_device, power_on
    from sim_bus.multicast import MulticastNetwork, MulticastReceiver

    def noise_of(joint: JointSpec) -> SensorNoise:
        return SensorNoise(current=current_noise, joint_torque=torque_noise,
                           seed=seed + robot.joints.index(joint))

    served = ServedRobot()
    try:
        for bus, joints in robot.buses().items():
            if is_ethercat(bus):
                on_line = sorted(joints, key=lambda joint: joint.address)
                devices = [make_device(joint.model, Payload(), noise_of(joint),
                                       eds_path=joint.eds, commissioned=True)
                           for joint in on_line]
                served.served += [(joint.name, device)
                                  for joint, device in zip(on_line, devices, strict=True)]
                served.lines.append(LineThread(bus, parse_bus_spec(bus)["channel"], devices,
                                               served.stop))
                continue
            config = parse_bus_spec(bus)
            # udp_multicast, which stands in for CAN on machines without SocketCAN: the lean
            # path (`sim_bus.multicast`), else python-can's and canopen's own
            served.networks.append(
                MulticastNetwork(config)
                if config["interface"] == "udp_multicast"
                else open_network(bus, robot.bitrates.get(bus)))
            for joint in joints:
                served.nodes.append(power_on(served.networks[-1], joint.model, Payload(),
                                             noise_of(joint), joint.address,
                                             clock=WallClock(), eds_path=joint.eds,
                                             commissioned=True,
                                             silence_timeout=silence_timeout))
                served.served.append((joint.name, served.nodes[-1].device))
        multicast = [n for n in served.networks if isinstance(n, MulticastNetwork)]
        if multicast:
            served.receiver = MulticastReceiver(multicast)
            served.receiver.start()
        for line in served.lines:
            line.start()
        for line in served.lines:
            line.wait_ready()
    except Exception:
        served.close()
        raise
    return served
