"""`CanOpenDrive`: the CiA 402 layer over the CANopen transport, what the commands build for
`--bus` and `--sim`."""

from collections.abc import Sequence
from pathlib import Path

import canopen

from driver.canopen_transport import DEFAULT_HEARTBEAT_MS, CanOpenTransport, open_network
from driver.cia402_drive import Cia402Drive
from driver.clock import Clock
from protocol.dictionary import StartupParameter

__all__ = ["CanOpenDrive", "open_network"]


class CanOpenDrive(Cia402Drive):
    """Drive `node_id` on `network` (which it owns and disconnects on close).

    `velocity_limit` (rad/s, the joint's) sets the encoder-glitch guard; `drive_gain` (N.m/A,
    the model's) converts currents for drives commanded in torque; `eds` is the drive's EDS
    (default: the shipped elbow drive); `clock` is what the bus's watchdogs measure time on
    (`driver.clock`: drive time in lock-step; default the wall clock); `startup` are objects
    written in PRE-OPERATIONAL and read back (see `Cia402Drive`).
    ProfileError if the EDS lacks what the loop needs (nothing is sent to the drive then).
    """

    def __init__(self, network: canopen.Network, node_id: int = 2, *, velocity_limit: float,
                 period: float = 1e-3, drive_gain: float | None = None,
                 current_max: float | None = None,
                 eds: str | Path | None = None, clock: Clock | None = None,
                 response_timeout: float | None = None,
                 heartbeat_ms: int = DEFAULT_HEARTBEAT_MS,
                 startup: Sequence[StartupParameter] = ()):
        transport = CanOpenTransport(network, node_id, eds=eds, clock=clock,
                                     response_timeout=response_timeout,
                                     heartbeat_ms=heartbeat_ms)
        try:
            super().__init__(transport, velocity_limit=velocity_limit, period=period,
                             drive_gain=drive_gain, current_max=current_max, startup=startup)
        except Exception:
            transport.close()
            raise

    @classmethod
    def open(cls, bus_spec: str, node_id: int = 2, **kwargs) -> "CanOpenDrive":
        network = open_network(bus_spec)
        try:
            return cls(network, node_id, **kwargs)
        except BaseException:
            network.disconnect()
            raise

    @property
    def node_id(self) -> int:
        return self.transport.node_id

    @property
    def node(self) -> canopen.RemoteNode:
        """canopen's view of the drive (its `sdo` for objects the loop does not use)."""
        return self.transport.node

    @property
    def network(self) -> canopen.Network:
        return self.transport.network
