"""The drive options: the bus as python-can spells it (`-i/--interface`, `-c/--channel`,
`-b/--bitrate` and its own configuration files and environment), the short `--bus` spec with
`ethercat:IFACE` for an EtherCAT line, `--sim`, `--node-id` on CAN and `--slave`/`--esi` on
EtherCAT, `--eds`, `--lockstep`, `--can-log` and `--rt-priority`: checked together before
anything is opened, then handed as typed values to the robot layer (`robot.wiring`), which
opens the drive."""

from __future__ import annotations

import argparse
import errno
import logging
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import can
import can.cli

from commands.file_options import Inputs, check_output_file, option_inputs
from commands.parsing import DEFAULT_NODE_ID, LINE_SLAVES, NODE_ID, SLAVE_POSITION, int_range
from model.parameters import ActuatorModel, Payload
from protocol.bus_spec import BusSpecError, is_ethercat, parse_bus_spec
from robot.can_log import CanLog
from robot.wiring import (
    Connection,
    DriveOpenError,
    open_can_drive,
    open_embedded_drive,
    open_line_drive,
)

if TYPE_CHECKING:
    from protocol.esi import EsiDevice
    from sim_bus.faults import Fault

DEFAULT_BUS = "vcan0"  # the documented default (README, DESIGN): SocketCAN vcan0
_PYTHON_CAN_KEYS = ("interface", "channel", "bitrate", "fd", "data_bitrate", "timing")


def add_bus_arguments(parser: argparse.ArgumentParser, sim: bool = True) -> None:
    """python-can's own bus options (`-i`, `-c`, `-b`, `--fd`, `--data-bitrate`, `--timing`,
    `--bus-kwargs`), the short `--bus` spec, `--node-id`, `--eds`, `--can-log`, the EtherCAT
    options; with `sim` (a master: actuatord, recorder), also `--sim`, `--lockstep` and the
    slave position `--slave`, without it (sim-bus serves a line) `--slaves`."""
    can.cli.add_bus_arguments(parser, group_title="CAN bus (python-can's options)")
    group = parser.add_argument_group(
        "drive", "Without --bus or -i/-c the bus is python-can's configuration (CAN_INTERFACE, "
                 "CAN_CHANNEL, CAN_BITRATE, CAN_CONFIG, ~/.canrc), else vcan0.")
    group.add_argument("--bus", metavar="SPEC",
                       help="short bus spec: vcan0 (SocketCAN), virtual:NAME, "
                            "udp_multicast:GROUP[:PORT], INTERFACE:CHANNEL for any "
                            "python-can interface (pcan:PCAN_USBBUS1, kvaser:0, "
                            "slcan:/dev/ttyACM0, ...), or ethercat:IFACE for an EtherCAT "
                            "line on that network interface (raw socket: root or "
                            "CAP_NET_RAW)")
    if sim:
        group.add_argument("--sim", action="store_true",
                           help="embedded virtual drive in this process (no bus needed)")
        group.add_argument("--lockstep", action="store_true",
                           help="with --sim or an EtherCAT bus: run as fast as the drive "
                                "answers (over EtherCAT the slaves' watchdog is switched off "
                                "and the virtual slave advances one period per frame; a CAN "
                                "drive on a bus runs in real time)")
    group.add_argument("--node-id", type=NODE_ID,
                       help=f"CANopen node id, 1..127 (default: {DEFAULT_NODE_ID}; CAN only)")
    group.add_argument("--eds", metavar="FILE",
                       help="the drive's EDS: standard CiA 402 objects unless it offers the "
                            "manufacturer current mode (default: the shipped elbow drive, "
                            "protocol/elbow_drive.eds)" + ("; with --sim the embedded drive "
                                                           "serves it too" if sim else ""))
    group.add_argument("--can-log", metavar="FILE",
                       help="log every CAN frame sent and received with python-can's writer "
                            "for the suffix: .log (candump), .asc, .blf, ... (CAN only)")
    line = parser.add_argument_group("EtherCAT (with --bus ethercat:IFACE)")
    if sim:
        line.add_argument("--slave", type=SLAVE_POSITION, metavar="N",
                          help="the drive's position on the line, 0-based in frame order "
                               "(default: 0)")
    else:
        line.add_argument("--slaves", type=LINE_SLAVES, metavar="N",
                          help="virtual drives on the line, 1..64 (default: 1); each its own "
                               "physics, noise seeded --seed + its position")
    line.add_argument("--esi", metavar="FILE",
                      help="the slave's ESI (EtherCAT slave information XML): identity, sync "
                           "managers and PDOs (default: the shipped elbow drive, "
                           "protocol/elbow_drive.xml)" + ("" if sim else "; the slaves' SII "
                                                          "is built from it"))


def add_real_time_argument(parser: argparse.ArgumentParser) -> None:
    from driver.clock import REAL_TIME_PRIORITY

    parser.add_argument("--rt-priority", type=int_range(0, 99), default=REAL_TIME_PRIORITY,
                        metavar="N",
                        help="SCHED_RR priority of the real-time loop, 1..99, 0: normal "
                             "scheduling (default: %(default)s; needs root or CAP_SYS_NICE, "
                             "else a warning; not used with --lockstep)")


def apply_real_time(args: argparse.Namespace, prog: str) -> None:
    """Real time only: the process (and the threads it starts from now on) at the asked
    SCHED_RR priority, so CPU-bound work beside it does not delay a cycle, and its memory
    locked (`driver.clock.lock_memory`) and the CPUs kept out of sleep states
    (`driver.clock.keep_cpus_awake`); each refusal is one warning and the run goes on."""
    if getattr(args, "lockstep", False) or not args.rt_priority:
        return
    from driver.clock import CPU_DMA_LATENCY, keep_cpus_awake, lock_memory, prefer_real_time

    refused = prefer_real_time(args.rt_priority)
    if refused is not None:
        logging.getLogger(prog).warning(
            "real-time priority %d refused (%s): running at normal priority, a busy host "
            "may delay cycles", args.rt_priority, refused)
    refused = lock_memory()
    if refused is not None:
        logging.getLogger(prog).warning(
            "memory lock refused (%s): a page fault may delay a cycle (raise RLIMIT_MEMLOCK, "
            "or run as root)", refused)
    refused = keep_cpus_awake()
    if refused is not None:
        logging.getLogger(prog).warning(
            "CPU wake-up latency request refused (%s: %s): an idle CPU may wake a cycle late "
            "(run as root)", CPU_DMA_LATENCY, refused)


# python-can's options (argparse keys as can.cli names them), absent unless given
_CAN_ONLY = (("-i", "interface"), ("-c", "channel"), ("-b", "bitrate"), ("--fd", "fd"),
             ("--data-bitrate", "data_bitrate"), ("--timing", "timing"),
             ("--bus-kwargs", "bus_kwargs"), ("--can-log", "can_log"))


def ethercat_interface(args: argparse.Namespace) -> str | None:
    """The network interface of `--bus ethercat:IFACE`; None for a CAN bus or --sim. Raises
    BusSpecError for an ethercat spec without a usable interface name."""
    bus = getattr(args, "bus", None)
    if bus is None or not is_ethercat(bus):
        return None
    return parse_bus_spec(bus)["channel"]


def check_drive_arguments(args: argparse.Namespace,
                          robot_buses: Iterable[str] | None = None) -> None:
    """Refuse a drive choice that cannot work, before anything is opened, and settle the
    defaults that depend on the bus (`--node-id` 2 on CAN, `--slave` 0 on EtherCAT).
    `robot_buses`: with --robot, the file's buses (lock-step needs every one to be EtherCAT
    when not --sim). Raises BusSpecError or ValueError naming the option."""
    sim = getattr(args, "sim", False)
    interface = ethercat_interface(args)
    if sim:
        named = [option for option, key in (("--bus", "bus"), ("-i", "interface"),
                                            ("-c", "channel"), ("-b", "bitrate"))
                 if getattr(args, key, None) is not None]
        if named:
            raise ValueError(f"--sim and {named[0]}: the embedded drive needs no bus")
    elif interface is None:
        bus_config(args)
    if interface is not None:
        for option, key in (*_CAN_ONLY, ("--node-id", "node_id")):
            if getattr(args, key, None) is not None:
                raise ValueError(f"--bus {args.bus} and {option}: {option} is for a CAN bus"
                                 + ("; an EtherCAT drive is found by --slave (0-based)"
                                    if key == "node_id" else ""))
        if getattr(args, "slave", None) is None and "slave" in args:
            args.slave = 0
        if getattr(args, "slaves", None) is None and "slaves" in args:
            args.slaves = 1
        load_esi_option(args)
    else:
        for option, key in (("--slave", "slave"), ("--slaves", "slaves"), ("--esi", "esi")):
            if getattr(args, key, None) is not None:
                raise ValueError(f"{option} is for an EtherCAT bus (--bus ethercat:IFACE)"
                                 + ("; a CAN drive is found by --node-id" if key == "slave"
                                    else ""))
        if args.node_id is None:
            args.node_id = DEFAULT_NODE_ID
    if getattr(args, "lockstep", False) and not sim:
        # a virtual EtherCAT slave advances one period per frame and its watchdog is off in
        # lock-step; a CAN drive on a bus keeps its own clock (heartbeats, SYNC silence)
        if robot_buses is None and interface is None:
            raise ValueError("--lockstep needs --sim or an EtherCAT bus: a CAN drive on a bus "
                             "runs in real time")
        for bus in robot_buses or ():
            if not is_ethercat(bus):
                raise ValueError(f"--lockstep needs --sim or EtherCAT buses only: bus {bus} is "
                                 "CAN, whose drives run in real time")
    if args.can_log is not None:
        check_can_log(args.can_log, option_inputs(args))


def load_esi_option(args: argparse.Namespace) -> EsiDevice | None:
    """The ESI an EtherCAT bus is read with: `--esi FILE` or the shipped one; None for a CAN
    bus or --sim. ValueError names the option and what is wrong in the file."""
    if ethercat_interface(args) is None:
        return None
    from protocol import esi_path
    from protocol.esi import EsiError, load_esi

    path = args.esi
    try:
        return load_esi(path if path is not None else esi_path())
    except EsiError as exc:
        raise ValueError(f"--esi {exc}") from None


def check_eds(path: str | None, drive_gain: float | None = None, *,
              master: bool = True, esi: EsiDevice | None = None) -> None:
    """--eds FILE: an EDS canopen reads (checked whole: `protocol.dictionary`), whose objects
    take the ESI's PDOs when there is one (`esi`), and, for a `master`, one that offers what
    the torque loop needs (`driver.profile`, the check the master repeats when it opens the
    drive), so a drive the loop cannot run is refused before anything is sent to it. Over
    EtherCAT (`esi`) the loop gets only what the ESI's PDOs carry, so the check is on the EDS
    seen through it, the shipped EDS included. ValueError names the option and every missing
    object."""
    if path is None and esi is None:
        return
    from driver.interface import ProfileError
    from driver.profile import select_profile
    from protocol import eds_path
    from protocol.dictionary import load_dictionary
    from protocol.esi import EsiError, check_against_dictionary, ethercat_dictionary

    try:
        dictionary = load_dictionary(path if path is not None else eds_path())
    except ValueError as exc:  # its error names the file
        raise ValueError(f"--eds {exc}") from None
    shown = f"--eds {path}" if path is not None else f"the shipped EDS {eds_path().name}"
    if esi is not None:  # the slave maps what the ESI's PDOs list into the EDS's objects
        try:
            check_against_dictionary(esi, dictionary)
        except EsiError as exc:
            raise ValueError(f"--esi {esi.source} with {shown}: {exc}") from None
    if master:
        if esi is not None:
            dictionary = ethercat_dictionary(dictionary, esi)
            shown += f" through the ESI's PDOs ({esi.name})"
        try:
            select_profile(dictionary, drive_gain)
        except ProfileError as exc:
            raise ValueError(f"{shown}: {exc}") from None


def bus_config(args: argparse.Namespace) -> dict:
    """python-can's Bus arguments from -i/-c/-b/... or `--bus`, completed by python-can's own
    configuration loading (environment, ~/.canrc); the documented default when nothing names
    an interface. Raises BusSpecError naming the option."""
    given = {key: getattr(args, key) for key in _PYTHON_CAN_KEYS if key in args}
    given.update(getattr(args, "bus_kwargs", {}))
    if args.bus is not None:
        if "interface" in given or "channel" in given:
            raise BusSpecError(f"--bus {args.bus} and -i/-c both name the bus: give one")
        given = {**parse_bus_spec(args.bus), **given}
    elif "interface" not in given and not _python_can_names_an_interface():
        given = {**parse_bus_spec(DEFAULT_BUS), **given}
    try:
        return dict(can.util.load_config(config=given))
    except (can.CanInterfaceNotImplementedError, ValueError, TypeError) as exc:
        raise BusSpecError(f"CAN bus configuration {given}: {exc}") from None


def _python_can_names_an_interface() -> bool:
    """Whether python-can's own configuration (can.rc, CAN_INTERFACE or CAN_CONFIG, the
    config files) names an interface."""
    sources = (can.rc, can.util.load_environment_config(), can.util.load_file_config())
    return any(source.get("interface") or source.get("bustype") for source in sources)


def check_can_log(path: str, inputs: Inputs = ()) -> None:
    """--can-log FILE: a suffix python-can writes (optionally .gz) in a folder that takes it,
    none of the command's `inputs`."""
    suffixes = Path(path).suffixes
    suffix = suffixes[-2] if len(suffixes) > 1 and suffixes[-1] == ".gz" else (
        suffixes[-1] if suffixes else "")
    # what python-can both writes and reads back (its .txt printer writes what no reader reads)
    writers = set(can.io.logger.MESSAGE_WRITERS) & set(can.io.player.MESSAGE_READERS)
    if suffix.lower() not in writers:
        raise ValueError(f"--can-log {path}: expected a file ending in "
                         f"{', '.join(sorted(writers))} (python-can's writers and readers)")
    check_output_file("--can-log", path, inputs)


def open_can_log(args: argparse.Namespace) -> CanLog:
    """The `--can-log` file, its frames named after the bus (`sim` for the --sim link)."""
    if getattr(args, "sim", False):
        return CanLog(args.can_log, "sim")
    config = bus_config(args)
    return CanLog(args.can_log, str(config.get("channel") or config["interface"]))


def open_drive(args: argparse.Namespace, model: ActuatorModel, sim_model: ActuatorModel,
               payload: Payload, schedule: Iterable[tuple[Fault, float]] = (),
               name: str = "joint", **timing) -> Connection:
    """The master drive for the bus or `--sim` the options name, with the embedded virtual
    drive and the CAN log when asked for (`robot.wiring` opens them), as a robot of one joint
    named `name`. Call after every option
    is checked: this is where the drive is touched.

    `model` is what the master knows of the joint; `sim_model` and `payload` are the virtual
    drive's physics (its hidden truth), `schedule` its injected faults; `timing` goes to the
    master (`period`, `response_timeout`). Raises DriveOpenError (exit code 1)."""
    from driver.clock import clock_for

    clock = clock_for(getattr(args, "lockstep", False))
    interface = None if args.sim else ethercat_interface(args)
    if interface is not None:
        return open_line_drive(args.bus, args.slave, model, esi=load_esi_option(args),
                               eds=args.eds, name=name, clock=clock, **timing)
    config = None if args.sim else bus_config(args)
    can_log = None
    if args.can_log is not None:
        try:
            can_log = open_can_log(args)
        except Exception as exc:
            raise DriveOpenError(f"--can-log {args.can_log}: {exc}") from exc
    if config is not None:
        try:
            return open_can_drive(config, args.node_id, model, eds=args.eds, can_log=can_log,
                                  name=name, clock=clock, **timing)
        except DriveOpenError as exc:
            if getattr(exc.__cause__, "errno", None) != errno.EAFNOSUPPORT:
                raise
            raise DriveOpenError(f"{exc} (this kernel has no SocketCAN: --sim runs the virtual "
                                 "drive in this process, --bus udp_multicast:239.0.0.1 reaches "
                                 "sim-bus on the same bus)") from exc
    return open_embedded_drive(model, sim_model, payload, args.node_id, seed=args.seed,
                               eds=args.eds, schedule=schedule, can_log=can_log,
                               name=name, clock=clock, **timing)
