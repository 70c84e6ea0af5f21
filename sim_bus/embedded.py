"""The virtual drive inside another program's process (`actuatord --sim`, `recorder --sim`).

The master's and the drive's canopen Networks are linked directly: a frame one sends is handed
to the other's `notify` in the sender's thread (canopen's documented hook for custom
back-ends). Every CANopen service runs as on a bus (NMT, SDO, PDO, SYNC, EMCY, heartbeat), but
a control cycle costs no thread hand-offs, which is what lets the embedded default keep a 1 kHz
rhythm in Python. `--bus virtual:NAME` still goes through python-can's virtual interface.
"""

import threading
import time
from pathlib import Path

import canopen

from model.parameters import ActuatorModel, Payload
from sim_bus.canopen_node import CanOpenNode
from sim_bus.device import Cia402Device
from sim_bus.plant import SensorNoise


class LinkedNetwork(canopen.Network):
    def __init__(self):
        super().__init__(None)
        self.peers: list[canopen.Network] = []
        self._periodic: list[_PeriodicFrame] = []

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        # canopen's own services send lists; every receiver here reads bytes
        frame, now = data if type(data) is bytes else bytes(data), time.time()
        for peer in self.peers:
            peer.notify(can_id, frame, now)

    def notify(self, can_id: int, data: bytes, timestamp: float) -> None:
        """canopen's dispatch to the subscribers, without its node scanner (nobody scans a
        link that has exactly one node behind it)."""
        for callback in self.subscribers.get(can_id, ()):
            callback(can_id, data, timestamp)

    def send_periodic(self, can_id: int, data: bytes, period: float,
                      remote: bool = False) -> "_PeriodicFrame":
        task = _PeriodicFrame(self, can_id, bytes(data), period)
        self._periodic.append(task)
        return task

    def disconnect(self) -> None:
        for task in self._periodic:
            task.stop()
        self._periodic.clear()


class _PeriodicFrame:
    """canopen's PeriodicMessageTask interface (stop, update) on a plain thread."""

    def __init__(self, network: LinkedNetwork, can_id: int, data: bytes, period: float):
        self._network, self._can_id, self.data, self._period = network, can_id, data, period
        self._stop = threading.Event()
        threading.Thread(target=self._run, daemon=True, name=f"periodic-0x{can_id:X}").start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._network.send_message(self._can_id, self.data)
            self._stop.wait(self._period)

    def update(self, data: bytes) -> None:
        self.data = bytes(data)

    def stop(self) -> None:
        self._stop.set()


class EmbeddedDrive:
    """A booted virtual drive and the network a master should use to reach it.

    `lockstep`: the drive's heartbeat (and every other watchdog of its node) counts cycles,
    as the master's must then too (`CanOpenDrive(..., lockstep=True)`).
    """

    def __init__(self, model: ActuatorModel, payload: Payload, noise: SensorNoise,
                 node_id: int = 2, *, lockstep: bool = False, eds_path: str | Path | None = None,
                 initial_position: float | None = None):
        self.network = LinkedNetwork()
        self.master_network = LinkedNetwork()
        self.network.peers.append(self.master_network)
        self.master_network.peers.append(self.network)
        self.device = Cia402Device(model, payload, noise, eds_path=eds_path,
                                   initial_position=initial_position, node_id=node_id)
        self.node = CanOpenNode(self.network, node_id, self.device, lockstep=lockstep)
        self.node.boot()

    def close(self) -> None:
        self.node.close()
        self.network.disconnect()
