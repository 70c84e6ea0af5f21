"""Robot files: which joints a robot has, where each drive sits and what model it follows.

A robot file is TOML that people edit by hand, so every error names the file, the joint and
the field. It is checked whole before any bus is opened: every model file loads, every EDS
loads and offers what the torque loop needs (through the shipped ESI's PDOs on EtherCAT), node
ids and slave positions are unique per bus, limits only narrow the model's, and every bus
carries its joints' cyclic traffic within its budget (`protocol.bus_load`), else the file is
refused with the load figure and the fastest period that would fit.

    [robot]
    name = "talos_arm_left"
    period_us = 1000                       # one SYNC per CAN bus (one frame per segment)

    [buses."udp_multicast:239.0.1.1:43210"]
    bitrate = 1000000                      # bit/s (default: 1 Mbit/s, classic CAN's ceiling)

    [buses."ethercat:eth1"]
    sync = "dc"                            # "dc": distributed clocks, SYNC0 every period;
                                           # "free_run" (default): SM-synchronous

    [[joints]]
    name = "arm_left_4_joint"
    bus = "udp_multicast:239.0.1.1:43210"  # vcan0, socketcan:can1, ethercat:eth1, ...
    node_id = 5                            # CANopen node id; `slave = N` (0-based) on EtherCAT
    model = "models/talos_arm_shoulder.toml"   # relative to this file; default: the elbow
    eds = "drive.eds"                      # optional: the drive's EDS (default: the shipped one)
    limits = { position_min = -2.0 }       # optional: narrows the model's limits
    weights = { position = 300 }           # optional: MPC cost weights
    reference = { kind = "setpoint", position = -1.0 }   # optional (default: a sinusoid
                                           # over the middle half of the joint's range)
    friction_sharpness = 10                # optional: the MPC's beta in tanh(beta qd), 1/(rad/s)
                                           # (default: the paper's 1000; see talos_arm.toml)
    drive_type = "shoulder"                # optional: the [drive_types] entry it is
    sdo = [{ index = 0x6072, value = 800 }]  # optional start-up parameters (below)

Start-up parameters (as ros2_canopen's `sdo` lists or an ENI's InitCmds): CoE / SDO objects
the master writes right after boot, in PRE-OP (PRE-OPERATIONAL on CAN), then reads back; a
drive that refuses one stops the start naming the joint, the object and the abort code. Each
is `{ index = 0x6072, subindex = 0, value = 800 }` (subindex defaults to 0), checked here
against the joint's EDS: the object exists, is writable, is not one the master sets itself,
and the value fits its data type and EDS limits. Per drive type, written first, then the
joint's own (which win for the same object):

    [drive_types.shoulder]
    sdo = [{ index = 0x6073, value = 900 }]
"""

import math
import tomllib
from dataclasses import dataclass, field, fields, replace
from importlib.resources import files
from pathlib import Path

from controller.problem import Weights
from controller.reference import Reference, ReferenceError, Sinusoid, reference_from_dict
from model.parameters import ActuatorModel, Limits, ModelFileError, load_model
from protocol import bus_load
from protocol import pdo as pdo_layout
from protocol.bus_spec import BusSpecError, is_ethercat, parse_bus_spec
from protocol.dictionary import StartupParameter
from protocol.input_files import (
    TEXT_MAX,
    InputFileError,
    check_input_file,
    present,
    read_input_file,
)

DEFAULT_BITRATE = bus_load.CAN_CLASSIC_MAX_BITRATE
DEFAULT_HEARTBEAT_MS = 100  # the drives' and the master's heartbeat (driver default)
# an EtherCAT line's synchronization: free run (each slave cycles as its outputs arrive) by
# default, because it asks nothing of the drives (a drive without distributed clocks, or one
# whose ESI has no DC op mode, runs it) and keeps what every robot file meant before `sync`
# existed; "dc" is what CST drives such as TALOS's run on, named in the file where wanted
ETHERCAT_SYNC_MODES = ("free_run", "dc")
DEFAULT_ETHERCAT_SYNC = "free_run"
MAX_JOINTS = 64  # TALOS has 32; a file with more is more likely a mistake than a robot
# default reference: the paper's 0.2 Hz over the middle half of the joint's range
DEFAULT_REFERENCE_FREQUENCY = 0.2  # Hz
DEFAULT_REFERENCE_SPAN = 0.25  # amplitude as a share of the position range


class RobotFileError(ValueError):
    """A robot file that cannot be used; the message names the file, joint and field."""


@dataclass(frozen=True)
class JointSpec:
    name: str
    bus: str
    address: int  # CANopen node id (1..127) or EtherCAT slave position (0-based)
    model: ActuatorModel  # limits already narrowed by the robot file
    eds: Path | None
    weights: dict[str, float]
    reference: Reference
    friction_sharpness: float | None = None  # the MPC's beta for this joint (None: default)
    startup: tuple[StartupParameter, ...] = ()  # written in PRE-OP, read back

    @property
    def on_ethercat(self) -> bool:
        return is_ethercat(self.bus)


@dataclass(frozen=True)
class RobotSpec:
    name: str
    period_us: int
    joints: tuple[JointSpec, ...]
    bitrates: dict[str, int]  # CAN bus spec -> bit/s
    source: Path
    syncs: dict[str, str] = field(default_factory=dict)  # EtherCAT bus spec -> sync mode

    def sync(self, bus: str) -> str:
        """An EtherCAT line's synchronization ("free_run" or "dc")."""
        return self.syncs.get(bus, DEFAULT_ETHERCAT_SYNC)

    def buses(self) -> dict[str, list[JointSpec]]:
        """Joints grouped by bus, in file order."""
        out: dict[str, list[JointSpec]] = {}
        for joint in self.joints:
            out.setdefault(joint.bus, []).append(joint)
        return out

    def bus_loads(self) -> list[bus_load.BusLoad]:
        """Each bus's cyclic load with the PDO layout the master configures."""
        frames = cyclic_frame_bytes()
        loads = []
        for bus, joints in self.buses().items():
            if is_ethercat(bus):
                loads.append(bus_load.ethercat_segment_load(bus, [sum(frames)] * len(joints),
                                                            self.period_us))
            else:
                loads.append(bus_load.can_bus_load(bus, [frames] * len(joints),
                                                   self.bitrates.get(bus, DEFAULT_BITRATE),
                                                   self.period_us, DEFAULT_HEARTBEAT_MS))
        return loads


def cyclic_frame_bytes() -> list[int]:
    """Data bytes of each PDO one joint exchanges per cycle (the command and the sample)."""
    return [layout.struct.size for layout in (*pdo_layout.DEFAULT_RPDOS,
                                               *pdo_layout.DEFAULT_TPDOS)]


def shipped_robots() -> list[str]:
    """The names of the robot files shipped with the package (`robots/*.toml`)."""
    return sorted(entry.name.removesuffix(".toml") for entry in files("robots").iterdir()
                  if entry.name.endswith(".toml"))


def robot_path(name_or_path: str | Path) -> Path:
    """The robot file `--robot` names: the path itself when it exists or is written as a path
    (a folder or a suffix in it), else the shipped robot of that name (`talos_arm` ->
    robots/talos_arm.toml in the installed package)."""
    path = Path(name_or_path)
    try:
        if path.exists() or path.suffix or len(path.parts) > 1:
            return path
    except OSError:  # a name too long for a path: the loader refuses it in one line
        return path
    shipped = Path(str(files("robots") / f"{path.name}.toml"))
    return shipped if shipped.is_file() else path


def load_robot(path: str | Path) -> RobotSpec:
    """Read and check a robot file (a path, or a shipped robot's name: see robot_path);
    RobotFileError names what is wrong."""
    path = robot_path(path)
    if not present(path):
        raise RobotFileError(f"{path}: robot file not found (a path, or one of the shipped "
                             f"robots: {', '.join(shipped_robots())})")
    try:
        doc = tomllib.loads(read_input_file(path, "a robot file (TOML)", TEXT_MAX).decode(
            "utf-8-sig"))
    except InputFileError as exc:
        raise RobotFileError(str(exc)) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise RobotFileError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:
        raise RobotFileError(f"{path}: nested too deeply for a robot file") from None
    _keys(path, "", doc, {"robot", "buses", "joints", "drive_types"}, {"robot", "joints"})
    robot = _table(path, "[robot]", doc["robot"])
    _keys(path, "[robot]", robot, {"name", "period_us"}, {"name"})
    name = _string(path, "[robot].name", robot["name"])
    period_us = robot.get("period_us", 1000)
    if isinstance(period_us, bool) or not isinstance(period_us, int) or not (
            100 <= period_us <= 100_000):
        raise RobotFileError(f"{path}: [robot].period_us: expected an integer 100..100000, "
                             f"got {period_us!r}")
    bitrates, syncs = _bus_settings(path, _table(path, "[buses]", doc.get("buses", {})))
    drive_types = _drive_types(path, _table(path, "[drive_types]", doc.get("drive_types", {})))
    entries = doc["joints"]
    if not isinstance(entries, list) or not entries:
        raise RobotFileError(f"{path}: [[joints]]: expected at least one joint")
    if len(entries) > MAX_JOINTS:
        raise RobotFileError(f"{path}: {len(entries)} joints; at most {MAX_JOINTS} accepted")
    joints: list[JointSpec] = []
    models: dict[Path | None, ActuatorModel] = {}
    dictionaries: dict[tuple[Path, bool], object] = {}
    for number, entry in enumerate(entries, start=1):
        joints.append(_joint(path, number, _table(path, f"joint {number}", entry), models,
                             dictionaries, drive_types))
    _unique(path, joints)
    used = {entry.get("drive_type") for entry in entries}
    for kind in drive_types:
        if kind not in used:
            raise RobotFileError(f"{path}: [drive_types.{kind}]: no joint is of this type")
    for bus in (*bitrates, *syncs):
        if bus not in {j.bus for j in joints}:
            raise RobotFileError(f"{path}: [buses.\"{bus}\"]: no joint is on this bus")
    spec = RobotSpec(name, period_us, tuple(joints), bitrates, path, syncs)
    for load in spec.bus_loads():
        if not load.fits:
            raise RobotFileError(
                f"{path}: bus {load.bus}: {load.joints} joints at {period_us} us need "
                f"{100 * load.load:.0f} % of {load.bitrate / 1e6:g} Mbit/s (worst-case "
                f"stuffing {100 * load.worst_case_load:.0f} %; budget "
                f"{100 * load.budget:.0f} %); the fastest period that fits is "
                f"{load.fastest_period_us} us, or spread the joints over more buses")
    return spec


def _joint(path: Path, number: int, entry: dict,
           models: dict[Path | None, ActuatorModel], dictionaries: dict,
           drive_types: dict[str, list]) -> JointSpec:
    name = _string(path, f"joint {number}.name", entry.get("name"))
    where = f"joint {name!r}"
    _keys(path, where, entry, {"name", "bus", "node_id", "slave", "model", "eds", "limits",
                               "weights", "reference", "friction_sharpness", "drive_type",
                               "sdo"}, {"name", "bus"})
    bus = _string(path, f"{where}.bus", entry["bus"])
    try:
        parse_bus_spec(bus)
    except BusSpecError as exc:
        raise RobotFileError(f"{path}: {where}.bus: {exc}") from None
    if is_ethercat(bus):
        if "node_id" in entry or "slave" not in entry:
            raise RobotFileError(f"{path}: {where}: a joint on EtherCAT needs `slave` (its "
                                 "0-based position in the segment), not `node_id`")
        address = _integer(path, f"{where}.slave", entry["slave"], 0, 65534)
    else:
        if "slave" in entry or "node_id" not in entry:
            raise RobotFileError(f"{path}: {where}: a joint on CAN needs `node_id` (1..127), "
                                 "not `slave`")
        address = _integer(path, f"{where}.node_id", entry["node_id"], 1, 127)
    model_path = _relative(path, f"{where}.model", entry.get("model"))
    if model_path not in models:
        try:
            if model_path is not None and present(model_path):  # else: "not found"
                check_input_file(model_path, "a model TOML", TEXT_MAX)
            models[model_path] = load_model(model_path)
        except (ModelFileError, InputFileError) as exc:
            raise RobotFileError(f"{path}: {where}.model: {exc}") from None
    model = models[model_path]
    eds = _relative(path, f"{where}.eds", entry.get("eds"))
    if eds is not None:
        _check_eds(path, where, eds, model, is_ethercat(bus), dictionaries)
    model = replace(model, limits=_limits(path, where, model.limits,
                                          _table(path, f"{where}.limits",
                                                 entry.get("limits", {}))))
    weights = _weights(path, where, _table(path, f"{where}.weights", entry.get("weights", {})))
    reference = _reference(path, where, entry.get("reference"), model.limits)
    sharpness = None
    if "friction_sharpness" in entry:
        sharpness = _number(path, f"{where}.friction_sharpness", entry["friction_sharpness"])
        if sharpness <= 0:
            raise RobotFileError(f"{path}: {where}.friction_sharpness: expected > 0, got "
                                 f"{sharpness}")
    startup = ()
    if "sdo" in entry or "drive_type" in entry:
        startup = _joint_startup(path, where, entry, drive_types,
                                 _dictionary(eds, is_ethercat(bus), dictionaries))
    return JointSpec(name, bus, address, model, eds, weights, reference, sharpness, startup)


def _drive_types(path: Path, table: dict) -> dict[str, list]:
    """[drive_types.NAME] tables: each's `sdo` list, checked per joint that uses it (against
    that joint's EDS)."""
    out = {}
    for kind, settings in table.items():
        where = f"[drive_types.{kind}]"
        settings = _table(path, where, settings)
        _keys(path, where, settings, {"sdo"}, {"sdo"})
        out[kind] = settings["sdo"]
    return out


def _joint_startup(path: Path, where: str, entry: dict, drive_types: dict[str, list],
                   dictionary) -> tuple[StartupParameter, ...]:
    """The joint's start-up parameters: its drive type's, then its own (which replace the
    type's for the same object), each checked against the joint's dictionary."""
    from protocol.dictionary import startup_problem

    lists = []
    if "drive_type" in entry:
        kind = _string(path, f"{where}.drive_type", entry["drive_type"])
        if kind not in drive_types:
            raise RobotFileError(f"{path}: {where}.drive_type: {kind!r} is not in "
                                 f"[drive_types] ({', '.join(sorted(drive_types)) or 'empty'})")
        lists.append((f"[drive_types.{kind}].sdo (for {where})", drive_types[kind]))
    if "sdo" in entry:
        lists.append((f"{where}.sdo", entry["sdo"]))
    merged: dict[tuple[int, int], StartupParameter] = {}
    for label, items in lists:
        if not isinstance(items, list):
            raise RobotFileError(f"{path}: {label}: expected a list of "
                                 "{ index, subindex, value } tables")
        for k, item in enumerate(items):
            at = f"{label}[{k}]"
            item = _table(path, at, item)
            _keys(path, at, item, {"index", "subindex", "value"}, {"index", "value"})
            parameter = StartupParameter(
                _integer(path, f"{at}.index", item["index"], 0x1000, 0xFFFF),
                _integer(path, f"{at}.subindex", item.get("subindex", 0), 0, 0xFF),
                item["value"])
            problem = startup_problem(dictionary, parameter)
            if problem is not None:
                raise RobotFileError(f"{path}: {at}: {problem}")
            merged[parameter[:2]] = parameter
    return tuple(merged.values())


def _check_eds(path: Path, where: str, eds: Path, model: ActuatorModel, ethercat: bool,
               checked: dict) -> None:
    """A joint's EDS loads (`protocol.dictionary` checks it whole) and offers what the torque
    loop needs with the joint's drive gain, through the shipped ESI's PDOs on EtherCAT: the
    check the master repeats when it opens the drive, done here so that a robot file is refused
    whole before any bus is opened. Each file is parsed once per load."""
    from driver.interface import ProfileError
    from driver.profile import select_profile
    from protocol.esi import EsiError

    try:
        select_profile(_dictionary(eds, ethercat, checked), model.parameters.drive_gain)
    except (ValueError, EsiError, ProfileError) as exc:
        raise RobotFileError(f"{path}: {where}.eds: {exc}") from None


def _dictionary(eds: Path | None, ethercat: bool, checked: dict):
    """The joint's dictionary as its master sees it (its EDS, the shipped one by default;
    through the shipped ESI on EtherCAT), parsed once per file and bus kind per load."""
    from protocol import eds_path, esi_path
    from protocol.dictionary import load_dictionary
    from protocol.esi import check_against_dictionary, ethercat_dictionary, load_esi

    key = ((eds if eds is not None else Path(eds_path())).resolve(), ethercat)
    if key not in checked:
        dictionary = load_dictionary(key[0])
        if ethercat:
            esi = load_esi(esi_path())
            check_against_dictionary(esi, dictionary)
            dictionary = ethercat_dictionary(dictionary, esi)
        checked[key] = dictionary
    return checked[key]


def default_reference(limits: Limits) -> Sinusoid:
    """A sinusoid over the middle half of the joint's range at 0.2 Hz, slowed if that would
    exceed half the velocity limit."""
    center = 0.5 * (limits.position_min + limits.position_max)
    amplitude = DEFAULT_REFERENCE_SPAN * (limits.position_max - limits.position_min)
    frequency = min(DEFAULT_REFERENCE_FREQUENCY,
                    0.5 * limits.velocity_max / (2 * math.pi * amplitude))
    return Sinusoid(center=round(center, 4), amplitude=round(amplitude, 4),
                    frequency=round(frequency, 4))


def _reference(path: Path, where: str, spec: object, limits: Limits) -> Reference:
    if spec is None:
        return default_reference(limits)
    try:
        return reference_from_dict(spec, limits)
    except ReferenceError as exc:
        raise RobotFileError(f"{path}: {where}.reference: {exc}") from None


def _limits(path: Path, where: str, model_limits: Limits, table: dict) -> Limits:
    names = [f.name for f in fields(Limits)]
    _keys(path, f"{where}.limits", table, set(names), set())
    values = vars(model_limits).copy()
    for key, value in table.items():
        number = _number(path, f"{where}.limits.{key}", value)
        narrower = (number >= values[key] if key == "position_min" else number <= values[key])
        if not narrower or (key != "position_min" and key != "position_max" and number <= 0):
            raise RobotFileError(f"{path}: {where}.limits.{key}: {number} must narrow the "
                                 f"model's {values[key]} (a robot file cannot widen a limit)")
        values[key] = number
    if not values["position_min"] < values["position_max"]:
        raise RobotFileError(f"{path}: {where}.limits: position_min must be below position_max")
    return Limits(**values)


def _weights(path: Path, where: str, table: dict) -> dict[str, float]:
    _keys(path, f"{where}.weights", table, set(Weights.__dataclass_fields__), set())
    out = {}
    for key, value in table.items():
        number = _number(path, f"{where}.weights.{key}", value)
        if number < 0:
            raise RobotFileError(f"{path}: {where}.weights.{key}: expected >= 0, got {number}")
        out[key] = number
    return out


def _bus_settings(path: Path, table: dict) -> tuple[dict[str, int], dict[str, str]]:
    """[buses."SPEC"]: a CAN bus's bitrate, an EtherCAT line's sync mode."""
    bitrates, syncs = {}, {}
    for bus, settings in table.items():
        where = f"[buses.\"{bus}\"]"
        settings = _table(path, where, settings)
        if is_ethercat(bus):
            if "bitrate" in settings:
                raise RobotFileError(f"{path}: {where}: an EtherCAT segment has no bitrate to "
                                     "set")
            _keys(path, where, settings, {"sync"}, set())
            if "sync" in settings:
                sync = settings["sync"]
                if sync not in ETHERCAT_SYNC_MODES:
                    raise RobotFileError(f"{path}: {where}.sync: expected one of "
                                         f"{', '.join(map(repr, ETHERCAT_SYNC_MODES))}, got "
                                         f"{sync!r}")
                syncs[bus] = sync
            continue
        _keys(path, where, settings, {"bitrate"}, set())
        if "bitrate" in settings:
            bitrates[bus] = _integer(path, f"{where}.bitrate", settings["bitrate"], 10_000,
                                     bus_load.CAN_CLASSIC_MAX_BITRATE)
    return bitrates, syncs


def _unique(path: Path, joints: list[JointSpec]) -> None:
    names, addresses = set(), set()
    for joint in joints:
        if joint.name in names:
            raise RobotFileError(f"{path}: joint {joint.name!r} is listed twice")
        names.add(joint.name)
        key = (joint.bus, joint.address)
        if key in addresses:
            kind = "slave position" if joint.on_ethercat else "node id"
            raise RobotFileError(f"{path}: joint {joint.name!r}: {kind} {joint.address} is "
                                 f"already used on {joint.bus}")
        addresses.add(key)


def _relative(path: Path, where: str, value: object) -> Path | None:
    if value is None:
        return None
    return path.parent / _string(path, where, value)


def _keys(path: Path, where: str, table: dict, allowed: set[str], required: set[str]) -> None:
    for key in table:
        if key not in allowed:
            raise RobotFileError(f"{path}: {where}{'.' if where else ''}{key}: unknown key; "
                                 f"expected one of {', '.join(sorted(allowed))}")
    for key in sorted(required - set(table)):
        raise RobotFileError(f"{path}: {where}{'.' if where else ''}{key}: missing")


def _table(path: Path, where: str, value: object) -> dict:
    if not isinstance(value, dict):
        raise RobotFileError(f"{path}: {where}: expected a table")
    return value


def _string(path: Path, where: str, value: object) -> str:
    if not isinstance(value, str) or not value.strip():
        raise RobotFileError(f"{path}: {where}: expected a non-empty string, got {value!r}")
    return value


def _number(path: Path, where: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise RobotFileError(f"{path}: {where}: expected a number, got {value!r}")
    number = float(value) if abs(value) < 1e300 else math.inf
    if not math.isfinite(number):
        raise RobotFileError(f"{path}: {where}: expected a finite number, got {value!r}")
    return number


def _integer(path: Path, where: str, value: object, low: int, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise RobotFileError(f"{path}: {where}: expected an integer {low}..{high}, "
                             f"got {value!r}")
    return value
