"""The virtual drive inside another program's process (`actuatord --sim`, `recorder --sim`):
a private python-can `virtual` channel, so the program's master talks real CANopen to it."""

import itertools
import os

import canopen

from model.parameters import ActuatorModel, Payload
from protocol.bus_spec import parse_bus_spec
from sim_bus.drive import VirtualDrive
from sim_bus.plant import SensorNoise

_count = itertools.count()


class EmbeddedDrive:
    def __init__(self, model: ActuatorModel, payload: Payload, noise: SensorNoise,
                 node_id: int = 2):
        self.bus_spec = f"virtual:embedded-{os.getpid()}-{next(_count)}"
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05  # s; how long closing waits for the receive thread
        self.network.connect(**parse_bus_spec(self.bus_spec))
        self.drive = VirtualDrive(self.network, node_id, model, payload, noise)
        self.drive.boot()

    def close(self) -> None:
        self.drive.close()
        self.network.disconnect()
