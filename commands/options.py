"""What the commands share: the parser with one-line errors, `--log-level`, the drive options
(the bus as python-can spells it: `-i/--interface`, `-c/--channel`, `-b/--bitrate` and its own
configuration files and environment, the short `--bus` spec with `ethercat:IFACE` for an
EtherCAT line, `--sim`, `--node-id` on CAN and `--slave`/`--esi` on EtherCAT, `--lockstep`,
`--can-log`, and the virtual drive's `--seed`, `--truth-effect`, `--inject-fault`), the one
place a master drive is opened (CANopen, EtherCAT or embedded), the payload and `NAME=VALUE`
options, output paths checked before a run, Zenoh key expressions and the Zenoh session options
(spelled like Zenoh's own tools: `--listen`, `--connect`, `--zenoh-config`,
`--no-multicast-scouting`), and the one way a usage error is reported.

Command-line text is parsed here and nowhere below: the library layers take typed values and
raise typed errors; a command turns those into one line on stderr and exit code 2, before it
touches a drive or creates a file.
"""

from __future__ import annotations

import argparse
import collections
import copy
import json
import logging
import math
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

import can
import can.cli
import zenoh

from model.effects import EFFECT_KEYS, EFFECT_NAMES
from model.parameters import GRAVITY, ActuatorModel, Payload
from protocol.bus_spec import BusSpecError, is_ethercat, parse_bus_spec
from sim_bus.faults import Fault

if TYPE_CHECKING:  # imported when a drive is opened: the dashboard needs neither
    from commands.robot_file import JointSpec, RobotSpec
    from driver.cia402_drive import Cia402Drive
    from driver.drive_group import DriveGroup
    from protocol.esi import EsiDevice
    from sim_bus.device import Cia402Device
    from sim_bus.embedded import EmbeddedBus


class CommandParser(argparse.ArgumentParser):
    """argparse whose errors are one line, `PROG: error: MESSAGE`, exit code 2 (the usage is
    one `--help` away)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def usage_error(prog: str, message: str) -> int:
    """Bad usage or input: one line on stderr naming the option or file; exit code 2."""
    print(f"{prog}: error: {message}", file=sys.stderr, flush=True)
    return 2


# --- argument types: a bad value is refused while parsing, naming its option ----------------

def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None


def finite_float(text: str) -> float:
    value = _number(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number")
    return value


def non_negative_float(text: str) -> float:
    value = _number(text)
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number >= 0")
    return value


def positive_float(text: str) -> float:
    value = _number(text)
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number > 0")
    return value


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def int_range(low: int, high: int) -> Callable[[str], int]:
    """An argparse type for an integer in [low, high]."""
    def parse(text: str) -> int:
        value = _integer(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{value}: expected {low}..{high}")
        return value

    parse.__name__ = f"integer {low}..{high}"
    return parse


def seed(text: str) -> int:
    """numpy's generators take seeds >= 0."""
    value = _integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{value}: expected an integer >= 0")
    return value


NODE_ID = int_range(1, 127)  # CiA 301 node ids
DEFAULT_NODE_ID = 2  # the elbow drive's
SLAVE_POSITION = int_range(0, 65534)  # 0-based positions on a line (SOEM counts to 65535)
LINE_SLAVES = int_range(1, 64)  # virtual slaves one sim-bus serves on a line (robot files: 64)
TCP_PORT = int_range(1, 65535)


# --- logging ---------------------------------------------------------------------------------

LOG_LEVELS = ("debug", "info", "warning", "error")


def add_logging_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--log-level", choices=LOG_LEVELS, default="warning",
                        help="what the libraries report on stderr (default: %(default)s); "
                             "errors always show")


class _Once(logging.Filter):
    """Passes each warning or error text once: a fault that a library logs and the command then
    reports (as is, or behind its own words: "drive failed: <the fault>") is read once, and a
    warning repeated every cycle does not flood the terminal."""

    def __init__(self) -> None:
        super().__init__()
        self._seen: set[str] = set()
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        text = record.getMessage()
        with self._lock:
            if text in self._seen or any(text.endswith(": " + seen) for seen in self._seen):
                return False
            self._seen.add(text)
        return True


def configure_logging(prog: str, level: str) -> None:
    """Logging for the whole process, once: `PROG: LEVEL: message` on stderr."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(f"{prog}: %(levelname)s: %(message)s"))
    handler.addFilter(_Once())
    logging.addLevelName(logging.DEBUG, "debug")
    logging.addLevelName(logging.INFO, "info")
    logging.addLevelName(logging.WARNING, "warning")
    logging.addLevelName(logging.ERROR, "error")
    logging.addLevelName(logging.CRITICAL, "critical")
    logging.basicConfig(level=level.upper(), handlers=[handler], force=True)


def job_error(prog: str, message: str) -> int:
    """The job failed (exit code 1): the reason goes through logging, so a fault the library
    already logged is read once."""
    logging.getLogger(prog).error("%s", message)
    return 1


# --- output paths: checked before the run, nothing created -----------------------------------

def check_output_file(option: str, path: str) -> Path:
    """A file this command will write: its folder exists and takes a new file, and the path is
    not a folder. Probed with a temporary file that is removed at once (permission bits say
    nothing when running as root). ValueError names the option."""
    target = Path(path)
    if target.is_dir():
        raise ValueError(f"{option} {path}: is a directory; expected a file path")
    folder = target.parent
    if not folder.is_dir():
        raise ValueError(f"{option} {path}: folder {folder} does not exist")
    _probe(option, path, folder)
    return target


def check_output_folder(option: str, path: str) -> Path:
    """A folder this command will create (if needed) and fill: the nearest existing ancestor
    takes new entries. ValueError names the option."""
    target = Path(path)
    if target.exists() and not target.is_dir():
        raise ValueError(f"{option} {path}: exists and is not a directory")
    existing = target
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ValueError(f"{option} {path}: {existing} is not a directory")
    _probe(option, path, existing)
    return target


def _probe(option: str, path: str, folder: Path) -> None:
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise ValueError(f"{option} {path}: cannot write in {folder}: "
                         f"{exc.strerror or exc}") from None


# --- Zenoh key expressions -------------------------------------------------------------------

def check_key_expr(option: str, text: str, wildcards: bool) -> str:
    """A Zenoh key expression (`wildcards` allows `*`, `**`, `$*`: subscriptions do, a
    publishing prefix does not). ValueError names the option and the rule broken."""
    if not wildcards and any(c in text for c in "*$"):
        raise ValueError(f"{option} {text!r}: expected a key prefix without wildcards "
                         "(*, **, $*), e.g. actuators/elbow")
    try:
        zenoh.KeyExpr(text)
    except Exception as exc:  # zenoh raises its own ZError; keep its reason, not its source
        reason = str(exc).split(" at /", 1)[0]
        raise ValueError(f"{option} {text!r}: not a Zenoh key expression: {reason}") from None
    return text


# --- the drive: a bus, or the virtual drive embedded in this process --------------------------

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
    SCHED_RR priority, so CPU-bound work beside it does not delay a cycle; a refusal is one
    warning and the run goes on at normal priority."""
    if getattr(args, "lockstep", False) or not args.rt_priority:
        return
    from driver.clock import prefer_real_time

    refused = prefer_real_time(args.rt_priority)
    if refused is not None:
        logging.getLogger(prog).warning(
            "real-time priority %d refused (%s): running at normal priority, a busy host "
            "may delay cycles", args.rt_priority, refused)


def add_virtual_drive_arguments(parser: argparse.ArgumentParser, faults: bool = True,
                                prefix: str = "--sim: ") -> None:
    """The virtual drive's own options: noise seed, hidden effects and, with `faults`,
    scheduled faults. `prefix` marks them as applying to `--sim` only."""

    parser.add_argument("--seed", type=seed, default=0,
                        help=f"{prefix}sensor-noise seed, >= 0 (default: 0)")
    parser.add_argument("--truth-effect", action="append", default=[], metavar="NAME:K=V,...",
                        help=f"{prefix}hidden effect in the virtual drive's physics, e.g. "
                             "stribeck:breakaway_friction=1.5,velocity=0.05 (repeatable; "
                             f"effects: {', '.join(EFFECT_NAMES)})")
    if faults:
        parser.add_argument("--inject-fault", action="append", default=[],
                            metavar="NAME@SECONDS",
                            help=f"{prefix}inject a fault at that drive time (repeatable): "
                                 + ", ".join(f.name.lower() for f in Fault if f is not Fault.NONE)
                                 + "; at run time, write its code to SDO 0x2010")


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
        check_can_log(args.can_log)


def load_esi_option(args: argparse.Namespace) -> EsiDevice | None:
    """The ESI an EtherCAT bus is read with: `--esi FILE` or the shipped one; None for a CAN
    bus or --sim. ValueError names the option and what is wrong in the file."""
    if ethercat_interface(args) is None:
        return None
    from protocol import esi_path
    from protocol.esi import EsiError, load_esi

    path = args.esi
    if path is not None and not Path(path).is_file():
        raise ValueError(f"--esi {path}: no such file")
    try:
        return load_esi(path if path is not None else esi_path())
    except EsiError as exc:
        raise ValueError(f"--esi {exc}") from None


def check_eds(path: str | None, drive_gain: float | None = None, *,
              master: bool = True, esi: EsiDevice | None = None) -> None:
    """--eds FILE: an EDS canopen reads and, for a `master`, one that offers what the torque
    loop needs (`driver.profile`, the check the master repeats when it opens the drive), so a
    drive the loop cannot run is refused before anything is sent to it. Over EtherCAT (`esi`)
    the loop gets only what the ESI's PDOs carry, so the check is on the EDS seen through it,
    the shipped EDS included. ValueError names the option and every missing object."""
    if path is None and (esi is None or not master):
        return
    from driver.interface import ProfileError
    from driver.profile import select_profile
    from protocol import eds_path
    from protocol.dictionary import load_dictionary
    from protocol.esi import ethercat_dictionary

    if path is not None and not Path(path).is_file():
        raise ValueError(f"--eds {path}: no such file")
    try:
        dictionary = load_dictionary(path if path is not None else eds_path())
    except ValueError as exc:  # its error names the file
        raise ValueError(f"--eds {exc}") from None
    if master:
        shown = f"--eds {path}" if path is not None else f"the shipped EDS {eds_path().name}"
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


def describe_bus(config: dict) -> str:
    channel = config.get("channel")
    return f"{config['interface']}:{channel}" if channel is not None else config["interface"]


def check_can_log(path: str) -> None:
    """--can-log FILE: a suffix python-can writes (optionally .gz) in a folder that takes it."""
    suffixes = Path(path).suffixes
    suffix = suffixes[-2] if len(suffixes) > 1 and suffixes[-1] == ".gz" else (
        suffixes[-1] if suffixes else "")
    writers = can.io.logger.MESSAGE_WRITERS
    if suffix.lower() not in writers:
        raise ValueError(f"--can-log {path}: expected a file ending in "
                         f"{', '.join(sorted(writers))} (python-can's writers)")
    check_output_file("--can-log", path)


class CanLog:
    """`--can-log`: every frame this process sends or receives, written in order by
    python-can's writer for the file's suffix."""

    def __init__(self, path: str, channel: str):
        self._writer = can.Logger(path)
        self._channel = channel  # named in the file for frames that carry none (those sent)
        self._lock = threading.Lock()  # the receive thread and the control thread both log
        self._open = True

    def write(self, msg: can.Message, is_rx: bool) -> None:
        logged = copy.copy(msg)
        logged.is_rx = is_rx
        if logged.channel is None:
            logged.channel = self._channel
        if not is_rx or not logged.timestamp:
            logged.timestamp = time.time()  # frames being sent carry no time yet
        with self._lock:
            if self._open:
                self._writer.on_message_received(logged)

    def stop(self) -> None:
        """Finish the file; idempotent."""
        with self._lock:
            if self._open:
                self._open = False
                self._writer.stop()


def open_can_log(args: argparse.Namespace) -> CanLog:
    """The `--can-log` file, its frames named after the bus (`sim` for the --sim link)."""
    if getattr(args, "sim", False):
        return CanLog(args.can_log, "sim")
    config = bus_config(args)
    return CanLog(args.can_log, str(config.get("channel") or config["interface"]))


class LoggedBus(can.BusABC):
    """A python-can bus that hands every frame it sends or receives to a CanLog, periodic
    frames included (python-can's thread-based periodic sender goes through `send`).

    Some interfaces hand a sender its own frames back (udp_multicast does, on one host): such
    an echo is logged once, as sent, so the file reads like a capture of the bus. A CANopen
    COB-ID has one sender, so a frame equal to one of ours just sent is our echo."""

    ECHO_WINDOW = 64  # frames sent whose echo may still come

    def __init__(self, bus: can.BusABC, can_log: CanLog):
        self._bus, self._log = bus, can_log
        self._sent: collections.deque = collections.deque(maxlen=self.ECHO_WINDOW)
        self._sent_lock = threading.Lock()
        super().__init__(channel=None)
        self.channel_info = bus.channel_info

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        with self._sent_lock:
            self._sent.append((msg.arbitration_id, bytes(msg.data)))
        self._bus.send(msg, timeout)
        self._log.write(msg, is_rx=False)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self._bus.recv(timeout)  # filtered by the bus itself
        if msg is not None:
            frame = (msg.arbitration_id, bytes(msg.data))
            with self._sent_lock:
                echo = frame in self._sent
                if echo:
                    self._sent.remove(frame)
            if not echo:
                self._log.write(msg, is_rx=True)
        return msg, True

    def shutdown(self) -> None:
        super().shutdown()
        self._bus.shutdown()


class _LinkTap:
    """A peer on one side of the --sim link (sim_bus.embedded.LinkedNetwork hands every frame
    its network sends to its peers' `notify`): what that side sends goes to the log, the
    master's frames as sent (Tx), the drive's as received (Rx)."""

    def __init__(self, can_log: CanLog, is_rx: bool):
        self._log, self._is_rx = can_log, is_rx

    def notify(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._log.write(can.Message(timestamp=timestamp, arbitration_id=can_id,
                                    is_extended_id=can_id > 0x7FF, data=bytes(data)),
                        self._is_rx)


def open_bus_network(args: argparse.Namespace, can_log: CanLog | None = None):
    """A connected canopen Network on the bus the options name (python-can's Bus, with its
    configuration); `can_log` gets every frame. Raises what python-can raises."""
    import canopen

    from driver.canopen_transport import NOTIFIER_CYCLE

    bus = can.Bus(ignore_config=True, **bus_config(args))
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


def fault_schedule(args: argparse.Namespace) -> list[tuple[Fault, float]]:
    """Every `--inject-fault NAME@SECONDS`; ValueError names the one at fault."""
    return [parse_fault(text) for text in args.inject_fault]


def parse_fault(text: str) -> tuple[Fault, float]:
    """'encoder_glitch@2.5' -> (Fault.ENCODER_GLITCH, 2.5 s of drive time)."""
    name, sep, when = text.partition("@")
    try:
        fault = Fault[name.upper()]
    except KeyError:
        names = ", ".join(f.name.lower() for f in Fault if f is not Fault.NONE)
        raise ValueError(f"--inject-fault {text}: fault {name!r}: expected one of "
                         f"{names}") from None
    try:
        seconds = float(when) if sep else 0.0
    except ValueError:
        raise ValueError(f"--inject-fault {text}: {when!r} is not a time in seconds") from None
    if fault is Fault.NONE or not (math.isfinite(seconds) and seconds >= 0):
        raise ValueError(f"--inject-fault {text}: expected NAME@SECONDS with a finite time "
                         ">= 0")
    return fault, seconds


class DriveOpenError(Exception):
    """The bus or the drive could not be opened (the job fails: exit code 1)."""


@dataclass
class Connection:
    """The master drive (CANopen or EtherCAT: the loop only sees the CiA 402 layer), the
    embedded virtual drive (`--sim`, else None) and the CAN log (`--can-log`, else None),
    closed together in that order."""

    drive: Cia402Drive
    sim: EmbeddedBus | None
    can_log: CanLog | None
    where: str  # the bus, as the user reads it
    address: str = ""  # the drive on it, as the user reads it: "node 2", "slave 0"

    def close(self) -> None:
        try:
            self.drive.close()
        finally:
            if self.sim is not None:
                self.sim.close()
            if self.can_log is not None:
                self.can_log.stop()


def open_drive(args: argparse.Namespace, model: ActuatorModel, sim_model: ActuatorModel,
               payload: Payload, schedule: Iterable[tuple[Fault, float]] = (),
               **timing) -> Connection:
    """The master drive for the bus or `--sim`, with the embedded virtual drive and the CAN log
    when asked for. Call after every option is checked: this is where the drive is touched.

    `model` is what the master knows of the joint (its velocity limit guards the encoder, its
    drive gain converts torque commands); `sim_model` and `payload` are the virtual drive's
    physics (its hidden truth), `schedule` its injected faults; `timing` goes to the master
    (`period`, `response_timeout`). Raises DriveOpenError (exit code 1)."""
    from driver.canopen_drive import CanOpenDrive

    lockstep = getattr(args, "lockstep", False)
    timing = {"lockstep": lockstep, "velocity_limit": model.limits.velocity_max,
              "drive_gain": model.parameters.drive_gain,
              "current_max": model.limits.current_max, **timing}

    interface = None if args.sim else ethercat_interface(args)
    if interface is not None:
        from driver.ethercat_drive import JointOnLine

        joint = JointOnLine(args.slave, timing.pop("velocity_limit"), timing.pop("drive_gain"),
                            current_max=timing.pop("current_max"))
        drive = _open_on_line(args.bus, interface, [joint], esi=load_esi_option(args),
                              eds=args.eds, **timing)[0]
        return Connection(drive, None, None, args.bus, f"slave {args.slave}")
    where = "--sim" if args.sim else describe_bus(bus_config(args))
    can_log = None
    if args.can_log is not None:
        try:
            can_log = open_can_log(args)
        except Exception as exc:
            raise DriveOpenError(f"--can-log {args.can_log}: {exc}") from exc
    if not args.sim:
        try:
            network = open_bus_network(args, can_log)
        except Exception as exc:
            if can_log is not None:
                can_log.stop()
            raise DriveOpenError(f"cannot open bus {where}: {exc}") from exc
        try:
            return Connection(CanOpenDrive(network, args.node_id, eds=args.eds, **timing), None,
                              can_log, where, f"node {args.node_id}")
        except Exception as exc:
            network.disconnect()
            if can_log is not None:
                can_log.stop()
            raise DriveOpenError(f"cannot use bus {where}: {exc}") from exc
    # the composition root is the one place a master meets the virtual drive
    from sim_bus.embedded import EmbeddedDrive
    from sim_bus.plant import SensorNoise

    sim = EmbeddedDrive(sim_model, payload, SensorNoise(seed=args.seed), args.node_id,
                        lockstep=lockstep, eds_path=args.eds)
    if can_log is not None:
        sim.master_network.peers.append(_LinkTap(can_log, is_rx=False))
        sim.network.peers.append(_LinkTap(can_log, is_rx=True))
    for fault, seconds in schedule:
        sim.device.schedule(fault, seconds)
    try:
        return Connection(CanOpenDrive(sim.master_network, args.node_id, eds=args.eds,
                                       **timing), sim, can_log, where, f"node {args.node_id}")
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

def parse_joint_fault(text: str, joints: Iterable[str]) -> tuple[str, Fault, float]:
    """`--inject-fault JOINT:NAME@SECONDS` with --robot: 'arm_left_4_joint:overcurrent_trip@2'
    -> (joint, fault, s of drive time); ValueError names the option and what was expected."""
    joint, sep, fault_text = text.rpartition(":")
    names = list(joints)
    if not sep or joint not in names:
        raise ValueError(f"--inject-fault {text}: with --robot expected JOINT:NAME@SECONDS, "
                         f"JOINT one of {', '.join(names)}")
    fault, seconds = parse_fault(fault_text)
    return joint, fault, seconds


@dataclass
class RobotConnection:
    """The joints' drive group and, with --sim, the embedded buses behind it; closed
    together (drives first, so every one is disabled while its bus still carries it)."""

    group: DriveGroup
    sim: list[EmbeddedBus]
    devices: dict[str, Cia402Device]  # joint -> its virtual drive (--sim only)

    def close(self) -> None:
        try:
            self.group.close()
        finally:
            for bus in self.sim:
                bus.close()


def open_robot(robot: RobotSpec, *, sim: bool, lockstep: bool, seed: int, period: float,
               response_timeout: float,
               faults: Iterable[tuple[str, Fault, float]] = ()) -> RobotConnection:
    """Every joint's drive, grouped by bus: one SYNC per CAN bus and one frame per EtherCAT
    line a cycle (`driver.drive_group`; a line's joints opened in slave order, the group
    keeps the file's joint order). With `sim`, each bus, CAN or EtherCAT, is an in-process
    CANopen link carrying one virtual drive per joint, commissioned for the joint's model
    (`sim_bus.commissioning`), its physics the joint's model, its noise seeded `seed` + the
    joint's index. An EtherCAT line has no in-process equivalent (its slaves answer on a raw
    interface), and the physics behind either bus is the same `Cia402Device`: what --sim does
    not exercise for those joints is the EtherCAT transport (cyclic synchronous torque through
    the ESI instead of the EDS's current mode). Raises DriveOpenError (exit 1)."""
    from driver.canopen_transport import CanOpenTransport, open_network
    from driver.cia402_drive import Cia402Drive
    from driver.drive_group import CanOpenBus, DriveGroup, Segment
    from driver.ethercat_drive import JointOnLine

    faults = list(faults)
    segments, embedded, devices = [], [], {}
    try:
        for bus, joints in robot.buses().items():
            if is_ethercat(bus) and not sim:
                on_line = sorted(joints, key=lambda joint: joint.address)
                segments.append(Segment(bus, []))
                drives = _open_on_line(bus, parse_bus_spec(bus)["channel"], [
                    JointOnLine(j.address, j.model.limits.velocity_max,
                                j.model.parameters.drive_gain, j.eds,
                                j.model.limits.current_max) for j in on_line],
                    period=period, lockstep=lockstep, response_timeout=response_timeout)
                segments[-1].joints = [(j.name, drive)
                                       for j, drive in zip(on_line, drives, strict=True)]
                continue
            # an embedded EtherCAT line: its joints at node ids 1.. in slave order
            addresses = ({j.name: k for k, j in enumerate(
                sorted(joints, key=lambda joint: joint.address), start=1)}
                if is_ethercat(bus) else {j.name: j.address for j in joints})
            if sim:
                from sim_bus.embedded import EmbeddedBus
                from sim_bus.plant import SensorNoise

                link = EmbeddedBus(lockstep=lockstep)
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
            for joint in joints:
                transport = CanOpenTransport(network, addresses[joint.name], eds=joint.eds,
                                             lockstep=lockstep,
                                             response_timeout=response_timeout,
                                             owns_network=False)
                segments[-1].joints.append((joint.name, Cia402Drive(
                    transport, velocity_limit=joint.model.limits.velocity_max, period=period,
                    drive_gain=joint.model.parameters.drive_gain,
                    current_max=joint.model.limits.current_max)))
        return RobotConnection(DriveGroup([j.name for j in robot.joints], segments), embedded,
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


def open_joint(robot: RobotSpec, joint: JointSpec, sim_model: ActuatorModel,
               payload: Payload, *, sim: bool, lockstep: bool, seed: int,
               **timing) -> Connection:
    """One joint of a robot file alone, the others not started (their drives stay as they
    powered up: switch on disabled, brake engaged; on an EtherCAT line they follow it to OP,
    with a zero controlword): its drive on its bus at its node id or slave position, or with
    `sim` a virtual drive commissioned for it on an in-process CANopen link (an EtherCAT
    joint's too, see `open_robot`), its physics `sim_model`. Raises DriveOpenError (exit
    1)."""
    from driver.canopen_drive import CanOpenDrive

    timing = {"lockstep": lockstep, "velocity_limit": joint.model.limits.velocity_max,
              "drive_gain": joint.model.parameters.drive_gain, "eds": joint.eds,
              "current_max": joint.model.limits.current_max, **timing}
    kind = "slave" if joint.on_ethercat else "node"
    if not sim and joint.on_ethercat:
        from driver.ethercat_drive import JointOnLine

        on_line = JointOnLine(joint.address, timing.pop("velocity_limit"),
                              timing.pop("drive_gain"), timing.pop("eds"),
                              timing.pop("current_max"))
        drive = _open_on_line(joint.bus, parse_bus_spec(joint.bus)["channel"], [on_line],
                              **timing)[0]
        return Connection(drive, None, None, joint.bus, f"slave {joint.address}")
    if not sim:
        try:
            return Connection(CanOpenDrive.open(joint.bus, joint.address, **timing), None, None,
                              joint.bus, f"node {joint.address}")
        except Exception as exc:
            raise DriveOpenError(f"cannot use bus {joint.bus}: {exc}") from exc
    from sim_bus.embedded import EmbeddedBus
    from sim_bus.plant import SensorNoise

    node_id = 1 if joint.on_ethercat else joint.address
    link = EmbeddedBus(lockstep=lockstep)
    try:
        link.add_drive(sim_model, payload, SensorNoise(seed=seed), node_id,
                       eds_path=joint.eds, commissioned=True)
        return Connection(CanOpenDrive(link.master_network, node_id, **timing), link,
                          None, "--sim", f"{kind} {joint.address}")
    except Exception as exc:
        link.close()
        raise DriveOpenError(f"cannot open the embedded drive of {joint.name}: {exc}") from exc


# --- the model, the payload and hidden effects -----------------------------------------------

def add_model_argument(parser: argparse.ArgumentParser,
                       help: str = "model TOML (default: the packaged paper defaults)") -> None:
    parser.add_argument("--model", help=help)


def add_payload_arguments(parser: argparse.ArgumentParser, mass_default: float | None = 0.0,
                          mass_help: str = "point mass carried by the link (kg)") -> None:
    parser.add_argument("--payload-mass", type=non_negative_float, default=mass_default,
                        metavar="KG", help=mass_help)
    parser.add_argument("--payload-position", metavar="X,Y",
                        help="payload position in the link frame (m), e.g. 0,0.05")


def payload_from_args(args: argparse.Namespace) -> Payload:
    return parse_payload(args.payload_mass, args.payload_position)


def parse_payload(mass: float, position: str | None) -> Payload:
    """Payload from `--payload-mass KG` and `--payload-position X,Y` (metres, link frame)."""
    from model.parameters import Payload

    x = y = 0.0
    if position is not None:
        parts = position.split(",")
        try:
            x, y = (float(v) for v in parts)
        except ValueError:
            x = y = math.nan
        if not (math.isfinite(x) and math.isfinite(y)):
            raise ValueError(f"--payload-position {position!r}: expected X,Y in metres, "
                             "e.g. 0,0.05")
    if mass > 0 and position is None:
        raise ValueError("payload mass given without --payload-position X,Y")
    return Payload(mass=mass, x=x, y=y)


def peak_joint_torque(model: ActuatorModel) -> float:
    """N.m: the most the drive can apply (drive_gain x current_max)."""
    return model.parameters.drive_gain * model.limits.current_max


def check_payload(model: ActuatorModel, payload: Payload) -> None:
    """Refuse a payload the drive could not hold: with it, the arm's gravity torque at its
    worst angle, g |(MX, MY)|, would exceed the drive's peak torque, so no controller keeps the
    joint anywhere but hanging (and absurd values overflow the physics)."""

    loaded = model.parameters.with_payload(payload)
    gravity = GRAVITY * math.hypot(loaded.first_moment_x, loaded.first_moment_y)
    peak = peak_joint_torque(model)
    if not gravity <= peak:
        raise ValueError(f"--payload-mass {payload.mass:g} at --payload-position "
                         f"{payload.x:g},{payload.y:g}: the arm's gravity torque would reach "
                         f"{gravity:.3g} N.m; expected a payload the drive can hold (at most "
                         f"{peak:g} N.m, drive_gain x current_max)")


def parse_effect_option(text: str) -> tuple[str, dict[str, float]]:
    """'stribeck:breakaway_friction=1.5,velocity=0.05' -> ('stribeck', {...})."""

    name, _, rest = text.partition(":")
    if name not in EFFECT_KEYS:
        raise ValueError(f"--truth-effect {text}: effect {name!r}: expected one of "
                         f"{', '.join(EFFECT_NAMES)}")
    table = {}
    for item in filter(None, rest.split(",")):
        key, sep, value = item.partition("=")
        if not sep or key not in EFFECT_KEYS[name]:
            raise ValueError(f"--truth-effect {text}: {item!r}: expected KEY=VALUE with KEY "
                             f"one of {', '.join(EFFECT_KEYS[name])}")
        try:
            table[key] = float(value)
        except ValueError:
            raise ValueError(f"--truth-effect {text}: {name}.{key}: {value!r} is not a "
                             "number") from None
    return name, table


def with_truth_effects(model: ActuatorModel, options: Iterable[str]) -> ActuatorModel:
    """The model with the `--truth-effect NAME:KEY=VALUE,...` effects added: the hidden "truth"
    a virtual drive can carry. ValueError names the option at fault."""

    parameters = model.parameters
    peak = peak_joint_torque(model)
    for option in options:
        name, table = parse_effect_option(option)
        for key, value in table.items():
            if EFFECT_KEYS[name][key][1] == "N.m" and not abs(value) <= peak:
                raise ValueError(f"--truth-effect {option}: {key} {value:g} N.m; expected at "
                                 f"most the drive's peak torque {peak:g} N.m")
        try:
            parameters = parameters.with_effect(name, {**parameters.effects.section(name),
                                                       **table})
        except (KeyError, ValueError) as exc:
            raise ValueError(f"--truth-effect {option}: {exc}") from None
    return replace(model, parameters=parameters)


def parse_assignments(items: Iterable[str], allowed: Iterable[str] | None,
                      what: str) -> dict[str, float]:
    """`NAME=VALUE` items (`--weight position=300`, `dashboard set weights position=300`) as
    {name: float}; ValueError names the item, and the allowed names when there are any."""
    allowed = list(allowed) if allowed is not None else None
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or (allowed is not None and name not in allowed):
            expected = f" with NAME one of {', '.join(allowed)}" if allowed is not None else ""
            raise ValueError(f"{what}: {item!r}: expected NAME=VALUE{expected}")
        try:
            out[name] = float(value)
        except ValueError:
            raise ValueError(f"{what}: {item!r}: {value!r} is not a number") from None
    return out


# --- Zenoh -----------------------------------------------------------------------------------

def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("Zenoh")
    group.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    group.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to connect to (repeatable)")
    group.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config file")
    group.add_argument("--no-multicast-scouting", action="store_true",
                       help="disable multicast scouting (peers only via --connect/--listen)")


def zenoh_config(args: argparse.Namespace) -> zenoh.Config:
    """A Zenoh config from the file (if any) with the command-line options applied on top.
    Raises ValueError naming the option at fault."""
    try:
        config = zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config else (
            zenoh.Config())
    except Exception as exc:  # zenoh raises its own ZError for unreadable or invalid files
        raise ValueError(f"--zenoh-config {args.zenoh_config}: {exc}") from None
    for option, key in (("listen", "listen/endpoints"), ("connect", "connect/endpoints")):
        endpoints = getattr(args, option)
        if endpoints:
            try:
                config.insert_json5(key, json.dumps(endpoints))
            except Exception as exc:
                raise ValueError(f"--{option} {' '.join(endpoints)}: {exc}") from None
    if args.no_multicast_scouting:
        config.insert_json5("scouting/multicast/enabled", "false")
    return config


def open_session(args: argparse.Namespace) -> zenoh.Session:
    config = zenoh_config(args)
    try:
        return zenoh.open(config)
    except Exception as exc:
        raise ValueError(f"cannot open the Zenoh session: {exc}") from None
