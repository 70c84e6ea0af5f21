"""EtherCAT Slave Information (ESI, ETG.2000) read into plain data: identity, mailbox and
sync manager layout, FMMU use, the PDOs and the CoE details. Only what the virtual slave's SII
image and the master's checks need; the object dictionary itself stays in the EDS."""

import copy
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path

from canopen.objectdictionary import ObjectDictionary, ODRecord, ODVariable

from protocol import ethercat as ec
from protocol.input_files import ESI_MAX, read_input_text

# ESI <DataType> names of the base types and their CoE data type codes (ETG.1000.6)
DATA_TYPES = {"BOOL": 0x0001, "SINT": 0x0002, "INT": 0x0003, "DINT": 0x0004, "USINT": 0x0005,
              "UINT": 0x0006, "UDINT": 0x0007, "REAL": 0x0008, "LREAL": 0x0011,
              "LINT": 0x0015, "ULINT": 0x001B}
SM_TYPES = {"MBoxOut": ec.SM_TYPE_MAILBOX_OUT, "MBoxIn": ec.SM_TYPE_MAILBOX_IN,
            "Outputs": ec.SM_TYPE_OUTPUTS, "Inputs": ec.SM_TYPE_INPUTS}
FMMU_USES = {"Outputs": ec.SII_FMMU_OUTPUTS, "Inputs": ec.SII_FMMU_INPUTS}
# bits of each base type: an entry's BitLen must be its type's
TYPE_BITS = {"BOOL": 1, "SINT": 8, "INT": 16, "DINT": 32, "USINT": 8, "UINT": 16, "UDINT": 32,
             "REAL": 32, "LREAL": 64, "LINT": 64, "ULINT": 64}
U8, U16, U32 = 0xFF, 0xFFFF, 0xFFFF_FFFF
# what the SII and an ESC can hold (ETG.2010, ETG.1000.4): the SII's size word counts KiBit
# (so 128-byte steps), an ESC has up to 16 sync managers and FMMUs in a 64 KiB address space,
# a PDO's entry count is one byte (0xFF reserved) and an entry is at most 64 bits
EEPROM_BYTES = (128, 65536)
MAX_SYNC_MANAGERS = 16
MAX_FMMUS = 16
MAX_PDO_ENTRIES = 254
MAILBOX_MIN = 16  # bytes: a mailbox header (6), a CoE header (2) and an expedited SDO (8)
RXPDO_INDICES = range(0x1600, 0x1800)
TXPDO_INDICES = range(0x1A00, 0x1C00)
# ETG.1020 "Error Settings" (0x10F1), an EtherCAT communication object no EDS carries: sub 1
# the local error reaction (read-only here: the slave's one reaction, SAFE-OP with the error
# indicator and its drive stopping as 0x6007 says), sub 2 the sync error counter limit (UINT16
# since SSC 5.11, as ETG.1020 has it; SSC's default MAX_SM_EVENT_MISSED = 4; 0 switches the
# check off, SSC 5.13), written by the master in PRE-OP like any start-up parameter
ERROR_SETTINGS = 0x10F1
LOCAL_ERROR_REACTION = 1
SYNC_ERROR_COUNTER_LIMIT = 2
SYNC_ERROR_COUNTER_LIMIT_DEFAULT = 4


class EsiError(ValueError):
    """An ESI file this code cannot use; the message names the element."""


@dataclass(frozen=True)
class PdoEntry:
    index: int
    subindex: int
    bits: int
    name: str
    data_type: int  # CoE data type code, 0 for a gap (index 0)

    @property
    def mapping_entry(self) -> int:
        """The 32-bit value of a 0x16xx/0x1Axx mapping sub-index."""
        return (self.index << 16) | (self.subindex << 8) | self.bits


@dataclass(frozen=True)
class Pdo:
    index: int
    name: str
    sync_manager: int
    entries: tuple[PdoEntry, ...]
    fixed: bool
    mandatory: bool

    @property
    def bits(self) -> int:
        return sum(e.bits for e in self.entries)


@dataclass(frozen=True)
class SyncManager:
    kind: str  # MBoxOut, MBoxIn, Outputs, Inputs
    start: int
    default_size: int
    min_size: int
    max_size: int
    control: int
    enable: bool

    @property
    def sm_type(self) -> int:
        return SM_TYPES[self.kind]


@dataclass(frozen=True)
class EsiDevice:
    vendor_id: int
    vendor_name: str
    product_code: int
    revision: int
    type_name: str  # order code
    name: str
    group: str
    profile: int
    fmmus: tuple[str, ...]
    sync_managers: tuple[SyncManager, ...]
    rxpdos: tuple[Pdo, ...]
    txpdos: tuple[Pdo, ...]
    coe_details: int  # ec.COE_DETAILS_* bits
    eeprom_bytes: int
    config_data: bytes  # SII words 0.. (PDI control, configuration, alias)
    source: str = ""  # the file it was read from, to name it in errors

    @property
    def identity(self) -> tuple[int, int, int]:
        return self.vendor_id, self.product_code, self.revision

    def sync_manager(self, kind: str) -> SyncManager:
        for sm in self.sync_managers:
            if sm.kind == kind:
                return sm
        raise EsiError(f"ESI device {self.type_name!r} has no <Sm>{kind}</Sm>")

    def sm_number(self, kind: str) -> int:
        return self.sync_managers.index(self.sync_manager(kind))

    @property
    def pdo_objects(self) -> frozenset[tuple[int, int]]:
        """(index, subindex) of every object the ESI's PDOs carry: what may be mapped into
        process data over EtherCAT."""
        return frozenset((e.index, e.subindex) for p in self.rxpdos + self.txpdos
                         for e in p.entries if e.index)

    def pdo_bytes(self, sync_manager: int) -> int:
        """Size of the default process data of one sync manager (its PDOs' entries)."""
        pdos = self.rxpdos + self.txpdos
        return sum(p.bits for p in pdos if p.sync_manager == sync_manager) // 8


def ethercat_dictionary(dictionary: ObjectDictionary, device: EsiDevice) -> ObjectDictionary:
    """The drive's dictionary (its EDS) as seen through its ESI: the same objects, mappable
    into process data only where the ESI's PDOs carry them. The CiA 402 layer picks its cyclic
    objects from this, so over EtherCAT it uses the ESI's (cyclic synchronous torque) layout
    and the slave accepts exactly that."""
    seen = copy.deepcopy(dictionary)
    allowed = device.pdo_objects
    for obj in seen.values():
        for var in obj.values() if not isinstance(obj, ODVariable) else (obj,):
            var.pdo_mappable = var.pdo_mappable and (var.index, var.subindex) in allowed
    if ERROR_SETTINGS not in seen:
        seen.add_object(error_settings())
    return seen


def error_settings() -> ODRecord:
    """The ETG.1020 Error Settings record (0x10F1) as an EtherCAT slave's dictionary has it,
    at its defaults."""
    record = ODRecord("Error Settings", ERROR_SETTINGS)
    for subindex, name, data_type, access, default in (
            (0, "Highest sub-index supported", 0x0005, "ro", 2),
            (LOCAL_ERROR_REACTION, "Local Error Reaction", 0x0007, "ro", 0),
            (SYNC_ERROR_COUNTER_LIMIT, "Sync Error Counter Limit", 0x0006, "rw",
             SYNC_ERROR_COUNTER_LIMIT_DEFAULT)):
        var = ODVariable(name, ERROR_SETTINGS, subindex)
        var.data_type, var.access_type, var.default = data_type, access, default
        record.add_member(var)
    return record


def check_against_dictionary(device: EsiDevice, dictionary: ObjectDictionary) -> None:
    """The ESI's PDOs fit the drive's dictionary (its EDS): each PDO's mapping object exists
    with a sub-index for every entry, and every entry is a PDO-mappable object of the entry's
    length, as the slave accepts them when the master writes the mapping over CoE. EsiError
    names the PDO and the entry."""
    for pdo in device.rxpdos + device.txpdos:
        where = f"PDO 0x{pdo.index:04X}"
        mapping = dictionary.get(pdo.index)
        if mapping is None or isinstance(mapping, ODVariable):
            raise EsiError(f"{where}: the EDS has no mapping object 0x{pdo.index:04X}")
        slots = len([k for k in mapping.subindices if k > 0])
        if len(pdo.entries) > slots:
            raise EsiError(f"{where}: {len(pdo.entries)} entries; the EDS's mapping object "
                           f"holds at most {slots}")
        for entry in pdo.entries:
            if not entry.index:
                continue
            obj = dictionary.get(entry.index)
            var = obj if isinstance(obj, ODVariable) and entry.subindex == 0 else (
                obj.get(entry.subindex) if obj is not None and not isinstance(obj, ODVariable)
                else None)
            if var is None or not var.pdo_mappable or len(var) != entry.bits:
                raise EsiError(f"{where}: entry 0x{entry.index:04X}:{entry.subindex:02X} "
                               f"({entry.bits} bits): expected a PDO-mappable object of the "
                               "EDS with that length")


def load_esi(path: str | Path) -> EsiDevice:
    """The first device of an ESI file, checked whole (ranges, and that its SII image fits its
    EEPROM) so nothing downstream meets a value it cannot encode. The file is stat'ed first
    (a regular file of at most 32 MiB). EsiError names the file and what is wrong."""
    try:
        text = read_input_text(path, "an ESI (EtherCAT slave information XML)", ESI_MAX)
    except ValueError as exc:
        raise EsiError(str(exc)) from None
    try:
        return replace(parse_esi(text), source=str(path))
    except EsiError as exc:
        raise EsiError(f"{path}: {exc}") from None


def parse_esi(text: str) -> EsiDevice:
    """An ESI's first device, every number in the range its field holds (ETG.2000 and the
    SII's) and its SII image within its EEPROM. EsiError names the element."""
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise EsiError(f"not XML: {exc}") from None
    except RecursionError:
        raise EsiError("not XML that can be read: nested too deeply") from None
    if root.tag != "EtherCATInfo":
        raise EsiError(f"root element is <{root.tag}>, expected <EtherCATInfo>")
    vendor = _required(root, "Vendor")
    device = _required(root, "Descriptions/Devices/Device")
    type_element = _required(device, "Type")
    mailbox = device.find("Mailbox/CoE")
    coe_details = 0
    if mailbox is not None:
        coe_details = ec.COE_DETAILS_SDO
        for attribute, bit in (("SdoInfo", ec.COE_DETAILS_SDO_INFO),
                               ("PdoAssign", ec.COE_DETAILS_PDO_ASSIGN),
                               ("PdoConfig", ec.COE_DETAILS_PDO_CONFIG),
                               ("CompleteAccess", ec.COE_DETAILS_COMPLETE_ACCESS)):
            if _boolean(mailbox.get(attribute, "0")):
                coe_details |= bit
    eeprom = device.find("Eeprom")
    config_text = eeprom.findtext("ConfigData", "") if eeprom is not None else ""
    try:
        config_data = bytes.fromhex(config_text)
    except ValueError:
        raise EsiError(f"Eeprom/ConfigData {config_text.strip()[:40]!r}: expected hexadecimal "
                       "bytes") from None
    parsed = EsiDevice(
        vendor_id=_number(_text(vendor, "Id"), "Vendor/Id", 0, U32),
        vendor_name=_text(vendor, "Name"),
        product_code=_number(type_element.get("ProductCode"), "Type@ProductCode", 0, U32),
        revision=_number(type_element.get("RevisionNo"), "Type@RevisionNo", 0, U32),
        type_name=(type_element.text or "").strip(),
        name=_text(device, "Name"),
        group=_text(device, "GroupType"),
        profile=_number(device.findtext("Profile/ProfileNo", "0"), "Profile/ProfileNo", 0, U16),
        fmmus=tuple(_fmmu(e) for e in device.findall("Fmmu")),
        sync_managers=tuple(_sync_manager(e) for e in device.findall("Sm")),
        rxpdos=tuple(_pdo(e) for e in device.findall("RxPdo")),
        txpdos=tuple(_pdo(e) for e in device.findall("TxPdo")),
        coe_details=coe_details,
        eeprom_bytes=_number(eeprom.findtext("ByteSize", "2048") if eeprom is not None
                             else "2048", "Eeprom/ByteSize", *EEPROM_BYTES),
        config_data=config_data,
    )
    _check_layout(parsed)
    return parsed


def _check_layout(device: EsiDevice) -> None:
    """What no single field shows: counts, the EEPROM size's steps, sync manager windows
    inside the ESC's address space, PDOs on a sync manager of their direction, and the SII
    image within the EEPROM."""
    from protocol.sii import build_sii  # sii reads EsiDevice: imported when checking

    if device.eeprom_bytes % 128:
        raise EsiError(f"Eeprom/ByteSize {device.eeprom_bytes}: expected a multiple of 128 "
                       "bytes (the SII counts KiBit)")
    if len(device.sync_managers) > MAX_SYNC_MANAGERS or len(device.fmmus) > MAX_FMMUS:
        raise EsiError(f"{len(device.sync_managers)} <Sm> and {len(device.fmmus)} <Fmmu>: an "
                       f"ESC has at most {MAX_SYNC_MANAGERS} of each")
    windows = []
    for number, sm in enumerate(device.sync_managers):
        if sm.start + max(sm.default_size, sm.max_size) > 0x10000:
            raise EsiError(f"Sm {sm.kind} at 0x{sm.start:04X} with {sm.max_size} bytes: "
                           "expected to end within the ESC's 64 KiB")
        mailbox = sm.kind in ("MBoxOut", "MBoxIn")
        if mailbox and sm.default_size < MAILBOX_MIN:
            raise EsiError(f"Sm {sm.kind} DefaultSize {sm.default_size}: expected at least "
                           f"{MAILBOX_MIN} bytes (a CoE SDO in a mailbox)")
        size = sm.default_size if mailbox else device.pdo_bytes(number)
        for other, start, end in windows:
            if sm.start < end and start < sm.start + size:
                raise EsiError(f"Sm {sm.kind} at 0x{sm.start:04X} ({size} bytes) overlaps Sm "
                               f"{other} at 0x{start:04X}; expected separate windows")
        windows.append((sm.kind, sm.start, sm.start + size))
    if not device.rxpdos or not device.txpdos:
        raise EsiError("expected at least one <RxPdo> and one <TxPdo> (a CiA 402 drive's "
                       "command and sample)")
    for kind, pdos, indices in (("Outputs", device.rxpdos, RXPDO_INDICES),
                                ("Inputs", device.txpdos, TXPDO_INDICES)):
        for pdo in pdos:
            where = f"PDO 0x{pdo.index:04X}"
            if pdo.index not in indices:
                raise EsiError(f"{where}: expected an index 0x{indices.start:04X}.."
                               f"0x{indices.stop - 1:04X} for a {kind[:-1].lower()} PDO")
            if not (pdo.sync_manager < len(device.sync_managers)
                    and device.sync_managers[pdo.sync_manager].kind == kind):
                raise EsiError(f"{where}: Sm={pdo.sync_manager}; expected the number of an "
                               f"<Sm>{kind}</Sm>")
            if len(pdo.entries) > MAX_PDO_ENTRIES:
                raise EsiError(f"{where}: {len(pdo.entries)} entries; at most "
                               f"{MAX_PDO_ENTRIES}")
    try:
        build_sii(device)
    except (ValueError, OverflowError) as exc:  # struct.error is a ValueError
        raise EsiError(f"its SII image: {exc}") from None


def _required(element: ET.Element, path: str) -> ET.Element:
    found = element.find(path)
    if found is None:
        raise EsiError(f"missing <{path}>")
    return found


def _text(element: ET.Element, path: str) -> str:
    return (_required(element, path).text or "").strip()


def _number(text: str | None, where: str, low: int, high: int) -> int:
    """ESI numbers: decimal or '#x' hexadecimal, within [low, high] (what the field holds)."""
    if text is None:
        raise EsiError(f"missing {where}")
    text = text.strip()
    try:
        value = int(text[2:], 16) if text[:2].lower() == "#x" else int(text)
    except ValueError:
        raise EsiError(f"{where}: {text[:40]!r} is not a number (decimal or #x hex)") from None
    if not low <= value <= high:
        raise EsiError(f"{where}: {text[:40]}: expected {low}..{high}")
    return value


def _boolean(text: str) -> bool:
    return text.strip().lower() in ("1", "true")


def _fmmu(element: ET.Element) -> str:
    use = (element.text or "").strip()
    if use not in FMMU_USES:
        raise EsiError(f"<Fmmu>{use}</Fmmu>: expected one of {', '.join(FMMU_USES)}")
    return use


def _sync_manager(element: ET.Element) -> SyncManager:
    kind = (element.text or "").strip()
    if kind not in SM_TYPES:
        raise EsiError(f"<Sm>{kind}</Sm>: expected one of {', '.join(SM_TYPES)}")
    size = _number(element.get("DefaultSize", "0"), f"Sm {kind} DefaultSize", 0, U16)
    return SyncManager(
        kind=kind,
        start=_number(element.get("StartAddress"), f"Sm {kind} StartAddress", 0, U16),
        default_size=size,
        min_size=_number(element.get("MinSize", str(size)), f"Sm {kind} MinSize", 0, U16),
        max_size=_number(element.get("MaxSize", str(size)), f"Sm {kind} MaxSize", 0, U16),
        control=_number(element.get("ControlByte"), f"Sm {kind} ControlByte", 0, U8),
        enable=_boolean(element.get("Enable", "0")),
    )


def _pdo(element: ET.Element) -> Pdo:
    index = _number(element.findtext("Index"), f"<{element.tag}> Index", 0, U16)
    where = f"<{element.tag}> 0x{index:04X}"
    entries = []
    for entry in element.findall("Entry"):
        entry_index = _number(entry.findtext("Index"), f"{where} Entry Index", 0, U16)
        type_name = (entry.findtext("DataType") or "").strip()
        if entry_index and type_name not in DATA_TYPES:
            raise EsiError(f"{where}: data type {type_name!r} is not one of "
                           f"{', '.join(DATA_TYPES)}")
        bits = _number(entry.findtext("BitLen"), f"{where} Entry BitLen", 1, 64)
        if entry_index and bits != TYPE_BITS[type_name]:
            raise EsiError(f"{where}: entry 0x{entry_index:04X} BitLen {bits}: expected "
                           f"{TYPE_BITS[type_name]} for {type_name}")
        entries.append(PdoEntry(
            index=entry_index,
            subindex=_number(entry.findtext("SubIndex", "0"), f"{where} Entry SubIndex", 0,
                             U8),
            bits=bits,
            name=(entry.findtext("Name") or "").strip(),
            data_type=DATA_TYPES.get(type_name, 0),
        ))
    return Pdo(
        index=index,
        name=(element.findtext("Name") or "").strip(),
        sync_manager=_number(element.get("Sm"), f"{where} Sm", 0, U8),
        entries=tuple(entries),
        fixed=_boolean(element.get("Fixed", "0")),
        mandatory=_boolean(element.get("Mandatory", "0")),
    )
