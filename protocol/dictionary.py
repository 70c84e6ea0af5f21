"""Questions asked of a drive's object dictionary (parsed from its EDS by canopen): does it
have an object, may an object be mapped into a PDO, what is its default. One answer for the
master (which EDS objects to use and map), the virtual drive (which mapping writes to accept)
and the EtherCAT side (the same CiA 402 dictionary over CoE)."""

import configparser
import io
import math
from pathlib import Path
from typing import NamedTuple

import canopen
from canopen.objectdictionary import ObjectDictionary, ODVariable, datatypes

from protocol import objects
from protocol.cia301 import SIGNED_TYPES
from protocol.input_files import EDS_MAX, read_input_file
from protocol.pdo import CODEC_BITS, MappedObject, split_mapping_entry

# every DataType canopen can read and write; anything else would reach the cycle as raw bytes
KNOWN_TYPES = frozenset(ODVariable.STRUCT_TYPES) | frozenset(datatypes.DATA_TYPES)
_ACCESS_TYPES = ("ro", "wo", "rw", "rwr", "rww", "const")
# the predefined record types (PDO communication and mapping, SDO, identity)
_RECORD_TYPES = frozenset(range(0x20, 0x24))
# objects the master's unit scaling divides by: a default, where given, must be > 0
_POSITIVE_DEFAULTS = ((objects.RATED_CURRENT, 0, "rated current"),
                      (objects.RATED_TORQUE, 0, "rated torque"),
                      (objects.ENCODER_RESOLUTION, 1, "encoder increments"),
                      (objects.ENCODER_RESOLUTION, 2, "motor revolutions"))


def load_dictionary(path: str | Path, node_id: int | None = None) -> ObjectDictionary:
    """Parse and check an EDS; `node_id` resolves `$NODEID` defaults (CANopen COB-IDs).
    The file is stat'ed first (a regular file of at most 8 MiB), read as UTF-8 (a byte-order
    mark dropped; Latin-1, as older vendor tools write, accepted) with any line ends, and
    checked whole (`check_dictionary`), so a drive is never opened with an EDS whose objects
    the cycle cannot decode. ValueError in one line naming the file."""
    data = read_input_file(path, "an EDS (CANopen electronic data sheet)", EDS_MAX)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = data.decode("latin-1")
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    raw = configparser.RawConfigParser(inline_comment_prefixes=(";",))  # as canopen reads it
    raw.optionxform = str
    try:
        raw.read_string(text, str(path))
    except configparser.Error as exc:
        raise ValueError(f"{path}: not a valid EDS: {_one_line(exc)}") from None
    _check_raw(raw, path)
    source = io.StringIO(text)
    source.name = "drive.eds"  # canopen picks its parser by the suffix; the content decides
    try:
        dictionary = canopen.import_od(source, node_id)
    except Exception as exc:  # canopen raises many kinds on a malformed file
        raise ValueError(f"{path}: not a valid EDS: {_one_line(exc)}") from None
    check_dictionary(dictionary, path)
    return dictionary


def _check_raw(raw: configparser.RawConfigParser, path: str | Path) -> None:
    """What canopen reads leniently, checked as written: every DataType names a CiA 301 type
    canopen can encode (canopen reads an unknown one as DOMAIN: a statusword that would reach
    the cycle as raw bytes), AccessType and PDOMapping are CiA 306's, and the default, value
    and limits of a number are numbers (canopen drops one it cannot parse, so the object
    would silently hold 0)."""
    for section in raw.sections():
        where = f"{path}: [{section}]"
        access = raw.get(section, "AccessType", fallback=None)
        if access is not None and access.strip().lower() not in _ACCESS_TYPES:
            raise ValueError(f"{where} AccessType={access.strip()[:20]}: expected one of "
                             f"{', '.join(_ACCESS_TYPES)}")
        mapping = raw.get(section, "PDOMapping", fallback=None)
        if mapping is not None and mapping.strip() not in ("0", "1"):
            raise ValueError(f"{where} PDOMapping={mapping.strip()[:20]}: expected 0 or 1")
        text = raw.get(section, "DataType", fallback=None)
        if text is None:
            continue
        try:
            data_type = int(text, 0)
        except ValueError:
            data_type = None
        record = raw.get(section, "ObjectType", fallback="0x7").strip() in ("0x8", "0x9",
                                                                            "0x08", "0x09")
        if data_type not in KNOWN_TYPES and not (record and data_type in _RECORD_TYPES):
            raise ValueError(f"{where} DataType={text.strip()}: expected a CiA 301 basic type "
                             "(0x0001..0x001B, e.g. 0x0006 UNSIGNED16)")
        parse = (_canopen_int if data_type in datatypes.INTEGER_TYPES + (datatypes.BOOLEAN,)
                 else float if data_type in datatypes.FLOAT_TYPES else None)
        for key in ("DefaultValue", "ParameterValue", "LowLimit", "HighLimit"):
            value = raw.get(section, key, fallback=None)
            if parse is None or value is None or not value.strip() or "$NODEID" in (
                    value.upper()):
                continue
            try:
                parse(value.strip())
            except ValueError:
                raise ValueError(f"{where} {key}={value.strip()[:20]}: expected a number for "
                                 f"DataType {text.strip()}") from None


def _canopen_int(text: str) -> int:
    """An EDS integer as canopen reads it (decimal or 0x hexadecimal, spaces ignored)."""
    return int(text.replace(" ", "").upper(), 0)


def _one_line(exc: Exception) -> str:
    """configparser's errors span lines (the file, the line number, the line): one line."""
    if isinstance(exc, configparser.MissingSectionHeaderError):
        return f"line {exc.lineno}: expected a [section] header before {exc.line.strip()!r:.60}"
    if isinstance(exc, configparser.ParsingError):
        number, line = exc.errors[0]
        return f"line {number}: expected KEY=VALUE or [section], got {line.strip()!r:.60}"
    if isinstance(exc, configparser.DuplicateSectionError | configparser.DuplicateOptionError):
        return f"line {exc.lineno}: {exc.message.split(':', 1)[-1].strip()}"
    return " ".join(f"{type(exc).__name__}: {exc}".split())[:300]


def _variables(dictionary: ObjectDictionary):
    for obj in dictionary.values():
        yield from (obj.values() if hasattr(obj, "values") else (obj,))


def integer_range(var: ODVariable) -> tuple[int, int]:
    """The values an integer object's DataType holds."""
    bits = len(var)
    if var.data_type in datatypes.SIGNED_TYPES:
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return 0, (1 << bits) - 1


def check_dictionary(dictionary: ObjectDictionary, source: str | Path) -> None:
    """Refuse what the drive and the master could not use, naming the object: a default
    outside its type's range or its own LowLimit..HighLimit, a non-positive rated current,
    rated torque or encoder resolution (the unit scaling divides by them), an inverted
    software position window 0x607D. ValueError in one line."""
    for var in _variables(dictionary):
        where = f"{source}: object 0x{var.index:04X}:{var.subindex:02X} ({var.name})"
        for label, value in (("DefaultValue", var.default), ("ParameterValue", var.value)):
            if value is None or var.data_type not in ODVariable.STRUCT_TYPES:
                continue
            if var.data_type in datatypes.FLOAT_TYPES:
                if not math.isfinite(value):
                    raise ValueError(f"{where}: {label} {value}: expected a finite number")
                continue
            low, high = integer_range(var)
            if var.data_type == datatypes.BOOLEAN:
                low, high = 0, 1
            if var.min is not None:
                low = max(low, var.min)
            if var.max is not None:
                high = min(high, var.max)
            if not low <= value <= high:
                raise ValueError(f"{where}: {label} {value}: expected {low}..{high} (its "
                                 "DataType and limits)")
    for index, subindex, name in _POSITIVE_DEFAULTS:
        var = variable(dictionary, index, subindex)
        value = None if var is None else next(
            (v for v in (var.value, var.default) if v is not None), None)
        if value is not None and not value > 0:
            raise ValueError(f"{source}: object 0x{index:04X}:{subindex:02X} ({name}) "
                             f"default {value}: expected > 0")
    low, high = (variable(dictionary, objects.SOFTWARE_POSITION_LIMIT, k) for k in (1, 2))
    if low is not None and high is not None:
        low_value, high_value = (next((v for v in (var.value, var.default) if v is not None),
                                      None) for var in (low, high))
        if low_value is not None and high_value is not None and not low_value < high_value:
            raise ValueError(f"{source}: software position limit 0x607D: min {low_value} >= "
                             f"max {high_value} increments; expected min < max")


def variable(dictionary: ObjectDictionary, index: int, subindex: int = 0) -> ODVariable | None:
    """The variable at index:subindex, or None when the dictionary lacks it."""
    if index not in dictionary:
        return None
    obj = dictionary[index]
    if isinstance(obj, ODVariable):
        return obj if subindex == 0 else None
    return obj[subindex] if subindex in obj else None


def has(dictionary: ObjectDictionary, index: int, subindex: int = 0) -> bool:
    return variable(dictionary, index, subindex) is not None


def mapped_object(var: ODVariable) -> MappedObject:
    return MappedObject(var.index, var.subindex, len(var), var.data_type in SIGNED_TYPES)


def mappable_object(dictionary: ObjectDictionary, entry: int) -> MappedObject:
    """Decode a 0x16xx/0x1Axx mapping entry against the dictionary: the object must exist,
    be marked PDO-mappable and have the entry's length. ValueError otherwise."""
    index, subindex, bits = split_mapping_entry(entry)
    var = variable(dictionary, index, subindex)
    if var is None or not var.pdo_mappable or len(var) != bits or bits not in CODEC_BITS:
        raise ValueError(f"object 0x{index:04X}:{subindex:02X} with {bits} bits is not mappable")
    return mapped_object(var)


def default_value(var: ODVariable) -> int | str | bytes:
    """What the object holds after a reset: its EDS ParameterValue, else DefaultValue, else 0
    (an EDS without a default, or a `$NODEID` default read without a node id)."""
    for value in (var.value, var.default):
        if value is not None:
            return value
    return 0


class StartupParameter(NamedTuple):
    """One CoE / SDO object the master writes in PRE-OP before the drive's configuration (as
    ros2_canopen's `sdo` lists or an ENI's InitCmds), then reads back."""

    index: int
    subindex: int
    value: int | float


# objects the master sets itself during bring-up and the cycle: a start-up value would be
# overwritten, or would fight the master (PDO communication and mapping, sync managers)
_MASTER_OWNED = (
    (range(objects.CONTROLWORD, objects.CONTROLWORD + 1), "the controlword"),
    (range(objects.MODES_OF_OPERATION, objects.MODES_OF_OPERATION + 1), "the mode"),
    (range(objects.TARGET_TORQUE, objects.TARGET_TORQUE + 1), "the torque target"),
    (range(objects.TARGET_CURRENT, objects.TARGET_CURRENT + 1), "the current target"),
    (range(objects.CYCLE_PERIOD_US, objects.CYCLE_PERIOD_US + 1), "the cycle period"),
    (range(objects.CONSUMER_HEARTBEAT, objects.SYNC_COUNTER_OVERFLOW + 1),
     "heartbeats and the SYNC counter"),
    (range(objects.RPDO_COMM, 0x1C00), "the PDO communication and mapping"),
    # sync manager types and PDO assignment; 0x1C30.. (sync mode, cycle) stay the user's,
    # as in an ENI's InitCmds
    (range(0x1C00, 0x1C30), "the sync manager types and PDO assignment"),
)


def startup_problem(dictionary: ObjectDictionary, parameter: StartupParameter) -> str | None:
    """What makes a start-up parameter unusable with this dictionary (the object missing,
    read-only, owned by the master, the value outside its type or its EDS limits), or None:
    the checks a robot file gets before any bus is opened."""
    index, subindex, value = parameter
    var = variable(dictionary, index, subindex)
    if var is None:
        return f"0x{index:04X}:{subindex:02X} is not in the drive's dictionary"
    where = f"0x{index:04X}:{subindex:02X} ({var.name})"
    owner = next((what for span, what in _MASTER_OWNED if index in span), None)
    if owner is not None:
        return f"{where}: the master sets {owner} itself"
    if var.access_type not in ("rw", "wo", "rww", "rwr"):
        return f"{where} is {var.access_type}, not writable"
    if var.data_type in datatypes.FLOAT_TYPES:
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(
                value):
            return f"{where}: expected a finite number, got {value!r}"
        return None
    if var.data_type not in ODVariable.STRUCT_TYPES:
        return f"{where}: only numeric objects can be start-up parameters"
    if isinstance(value, bool) or not isinstance(value, int):
        return f"{where}: expected an integer, got {value!r}"
    low, high = (0, 1) if var.data_type == datatypes.BOOLEAN else integer_range(var)
    if not low <= value <= high:
        return f"{where}: {value} is outside its data type's {low}..{high}"
    if var.min is not None and value < var.min or var.max is not None and value > var.max:
        return f"{where}: {value} is outside the EDS limits {var.min}..{var.max}"
    return None
