"""Questions asked of a drive's object dictionary (parsed from its EDS by canopen): does it
have an object, may an object be mapped into a PDO, what is its default. One answer for the
master (which EDS objects to use and map), the virtual drive (which mapping writes to accept)
and the EtherCAT side (the same CiA 402 dictionary over CoE)."""

from pathlib import Path

import canopen
from canopen.objectdictionary import ObjectDictionary, ODVariable

from protocol.cia301 import SIGNED_TYPES
from protocol.pdo import CODEC_BITS, MappedObject, split_mapping_entry


def load_dictionary(path: str | Path, node_id: int | None = None) -> ObjectDictionary:
    """Parse an EDS; `node_id` resolves `$NODEID` defaults (CANopen COB-IDs). ValueError
    names the file when it is not an EDS canopen can read."""
    try:
        return canopen.import_od(str(path), node_id)
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read EDS: {exc}") from None
    except Exception as exc:  # configparser and canopen raise many kinds on a malformed file
        raise ValueError(f"{path}: not a valid EDS: {exc}") from None


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
