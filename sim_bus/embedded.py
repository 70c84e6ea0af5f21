"""The virtual drive inside another program's process (`actuatord --sim`, `recorder --sim`).

The master's and the drive's canopen Networks are linked directly: a frame one sends is handed
to the other's `notify` in the sender's thread (canopen's documented hook for custom
back-ends). Every CANopen service runs as on a bus (NMT, SDO, PDO, SYNC, EMCY, heartbeat), but
a control cycle costs no thread hand-offs, which is what lets the embedded default keep a 1 kHz
rhythm in Python. `--bus virtual:NAME` still goes through python-can's virtual interface.
"""

import threading
import time
from collections.abc import Sequence
from pathlib import Path

import canopen

from model.dynamics import rest_position
from model.parameters import ActuatorModel, Payload
from sim_bus.canopen_node import CanOpenNode
from sim_bus.canopen_watchdogs import DEFAULT_SILENCE_TIMEOUT, Clock
from sim_bus.commissioning import drive_settings
from sim_bus.device import Cia402Device
from sim_bus.plant import SensorNoise


class LinkedNetwork(canopen.Network):
    """One end of the link. It counts the frames it receives and keeps the last one's stamp
    itself (`frames`, `last_stamp`: what `driver.canopen_health.BusWatch` judges the bus's
    load by, `counts_frames`): on a network that does not, the watch wraps `notify`, one
    more Python call (a closure's) for each frame, five a cycle of a lone drive (SYNC,
    RPDO, three TPDOs). A peer is anything with canopen's `notify` (a log's tap too)."""

    counts_frames = True

    def __init__(self):
        super().__init__(None)
        self.peers: list = []  # each with `notify`
        self._periodic: list[_PeriodicFrame] = []
        self.frames = 0  # received
        self.last_stamp = 0.0  # of the last frame received

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        # canopen's own services send lists; every receiver here reads bytes (a whole
        # slice of bytes is the same object: no copy)
        frame = data if type(data) is bytes else bytes(data)
        self.send_slices(frame, ((can_id, 0, len(frame)),))

    def send_slices(self, data: bytes, frames: Sequence[tuple[int, int, int]]) -> None:
        """Several frames in one call, in order, each `(can_id, start, stop)` a slice of
        `data` (a drive's TPDOs cut from one packed buffer, a master's RPDOs from its output
        image), each to every peer before the next, with one stamp (they leave together),
        without a Python call and a stamp per frame (a lone drive's three TPDOs and its RPDO
        are four of a cycle's five frames). `send_message` is one of them."""
        now, peers = time.time(), self.peers
        for can_id, start, stop in frames:
            frame = data[start:stop]
            for peer in peers:
                if type(peer) is LinkedNetwork:  # its `notify`, inline: a call fewer a frame
                    peer.frames += 1
                    peer.last_stamp = now
                    for callback in peer.subscribers.get(can_id, ()):
                        callback(can_id, frame, now)
                else:
                    peer.notify(can_id, frame, now)

    def notify(self, can_id: int, data: bytes, timestamp: float) -> None:
        """canopen's dispatch to the subscribers, without its node scanner (nobody scans a
        link that has exactly one node behind it), the frame counted."""
        self.frames += 1
        self.last_stamp = timestamp
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


class EmbeddedBus:
    """Virtual drives on one in-process bus: the drives' network linked to the one a master
    should use, and a `Cia402Device` exposed by a `CanOpenNode` per drive. Several nodes on
    one network share its frames as on a real bus: one SYNC reaches them all.

    `clock` (`driver.clock.clock_for`): each drive's own time is made from it, so its
    heartbeats and every other watchdog count the SYNCs it took in lock-step (as the master's
    must then too), the wall clock in real time.
    """

    def __init__(self, *, clock: Clock):
        self.clock = clock
        self.network = LinkedNetwork()
        self.master_network = LinkedNetwork()
        self.network.peers.append(self.master_network)
        self.master_network.peers.append(self.network)
        self.nodes: list[CanOpenNode] = []

    def add_drive(self, model: ActuatorModel, payload: Payload, noise: SensorNoise,
                  node_id: int, *, eds_path: str | Path | None = None,
                  initial_position: float | None = None,
                  commissioned: bool = False) -> Cia402Device:
        """Power on a drive at `node_id` on this bus (see `power_on`)."""
        # no SYNC-silence watch: the master shares this process, so it cannot die apart from
        # the drive, and a stall of the whole process (GC, a loaded host) is not a lost master
        node = power_on(self.network, model, payload, noise, node_id, clock=self.clock,
                        eds_path=eds_path, initial_position=initial_position,
                        commissioned=commissioned, silence_timeout=None)
        self.nodes.append(node)
        return node.device

    def close(self) -> None:
        for node in self.nodes:
            node.close()
        self.network.disconnect()


def power_on(network: canopen.Network, model: ActuatorModel, payload: Payload,
             noise: SensorNoise, node_id: int, *, clock: Clock,
             eds_path: str | Path | None = None, initial_position: float | None = None,
             commissioned: bool = False,
             silence_timeout: float | None = DEFAULT_SILENCE_TIMEOUT) -> CanOpenNode:
    """A virtual drive at `node_id` on `network` (embedded or a python-can bus), booted.
    `commissioned`: its window and currents follow the model's limits
    (`sim_bus.commissioning`) instead of the EDS's elbow values, and the joint starts inside
    its limits (at rest if gravity lets it hang there, else at the middle of its range).
    `clock`, `silence_timeout`: see `CanOpenNode`."""
    device = make_device(model, payload, noise, node_id=node_id, eds_path=eds_path,
                         initial_position=initial_position, commissioned=commissioned)
    node = CanOpenNode(network, node_id, device, clock=clock,
                       silence_timeout=silence_timeout)
    node.boot()
    return node


def make_device(model: ActuatorModel, payload: Payload, noise: SensorNoise, *,
                node_id: int | None = None, eds_path: str | Path | None = None,
                initial_position: float | None = None,
                commissioned: bool = False) -> Cia402Device:
    """A powered-on virtual drive, for any bus (see `power_on` for `commissioned`): the
    same drive whether a CANopen node or an EtherCAT slave exposes it."""
    if commissioned and initial_position is None:
        initial_position = _start_position(model, payload)
    device = Cia402Device(model, payload, noise, eds_path=eds_path,
                          initial_position=initial_position, node_id=node_id)
    if commissioned:
        device.store(drive_settings(model.limits, device.increments_per_rad))
    return device


def _start_position(model: ActuatorModel, payload: Payload) -> float:
    limits = model.limits
    rest = rest_position(model.parameters.with_payload(payload).packed())
    if limits.position_min <= rest <= limits.position_max:
        return rest
    return 0.5 * (limits.position_min + limits.position_max)


class EmbeddedDrive(EmbeddedBus):
    """One booted virtual drive (`device`, `node`) and the network a master should use to
    reach it, its values from the EDS as shipped."""

    def __init__(self, model: ActuatorModel, payload: Payload, noise: SensorNoise,
                 node_id: int = 2, *, clock: Clock, eds_path: str | Path | None = None,
                 initial_position: float | None = None):
        super().__init__(clock=clock)
        self.device = self.add_drive(model, payload, noise, node_id, eds_path=eds_path,
                                     initial_position=initial_position)
        self.node = self.nodes[0]
