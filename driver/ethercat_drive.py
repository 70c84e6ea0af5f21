"""CiA 402 drives on an EtherCAT line: the transport-neutral CiA 402 layer over one
`EthercatTransport` per slave, all sharing the line's master (one frame per cycle for every
joint). What the commands build for `--bus ethercat:IFACE`."""

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pysoem

from driver.cia402_drive import Cia402Drive
from driver.clock import DriveClock, WallClock
from driver.ethercat_transport import open_ethercat_transports
from protocol.dictionary import StartupParameter
from protocol.esi import EsiDevice


@dataclass(frozen=True)
class JointOnLine:
    """One joint's drive on the line: its slave position (0-based, in line order), its
    velocity limit (rad/s, for the sample guard), its model's drive gain (N.m/A, to command
    current through target torque 0x6071), where a robot file names one, its own EDS (else
    the line's `eds`), the most current its controller commands (A, checked at start), and
    the joint's name (named with its slave in the line's reports), and its start-up parameters
    (written in PRE-OP, read back: `driver.cia402_drive.Cia402Drive`)."""

    position: int
    velocity_limit: float
    drive_gain: float
    eds: str | Path | None = None
    current_max: float | None = None
    name: str | None = None
    startup: tuple[StartupParameter, ...] = ()


def open_ethercat_drives(interface: str, joints: Sequence[JointOnLine], *,
                         period: float = 1e-3, clock: WallClock | DriveClock | None = None,
                         esi: str | Path | EsiDevice | None = None,
                         eds: str | Path | None = None, response_timeout: float | None = None,
                         watchdog: float | None = None,
                         open_master: Callable[[], Any] = pysoem.Master,
                         sync: str = "free_run") -> list[Cia402Drive]:
    """The joints' drives on the line at `interface`, not started. Start every one before the
    first `sync` of any: the line goes to OP when the last is mapped, and the first `sync` of
    a cycle sends that cycle's frame for all of them (call each drive's `sync` once a cycle,
    then command each). `clock` a DriveClock: the slaves' watchdog is off and a cycle may take
    any wall time; `watchdog` (s) sets it in real time (default the ESC's 100 ms); `clock`,
    `open_master` and `sync` ("free_run" or "dc"): see `driver.ethercat_master.EthercatMaster`.
    """
    transports = open_ethercat_transports(
        interface, [j.position for j in joints], clock=clock, esi=esi,
        eds=[j.eds if j.eds is not None else eds for j in joints],
        response_timeout=response_timeout, watchdog=watchdog, open_master=open_master,
        names=[j.name for j in joints], sync=sync)
    drives = []
    try:
        for joint, transport in zip(joints, transports, strict=True):
            drives.append(Cia402Drive(transport, velocity_limit=joint.velocity_limit,
                                      current_max=joint.current_max,
                                      period=period, drive_gain=joint.drive_gain,
                                      startup=joint.startup))
    except Exception:
        for transport in transports:
            transport.close()
        raise
    return drives


def open_ethercat_drive(interface: str, joint: JointOnLine, **kwargs) -> Cia402Drive:
    """One joint alone on its line (see `open_ethercat_drives`)."""
    return open_ethercat_drives(interface, [joint], **kwargs)[0]
