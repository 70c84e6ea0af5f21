"""What the slave's CoE server reaches: the device's objects (its EDS dictionary) plus the
EtherCAT communication objects the ESI defines, with EtherCAT's rules on top.

- 0x1C00 sync manager types: read-only, from the ESI's sync managers.
- 0x1C12 / 0x1C13 PDO assignment of SM2 / SM3: the ESI's PDOs, changeable in PRE-OP only,
  sub-index 0 first set to 0 (ETG.1000.6).
- 0x1600.. / 0x1A00.. PDO mapping: held by the device (it validates the entries), changeable in
  PRE-OP only, sub-index 0 first set to 0, only objects the ESI's PDOs carry, an RxPDO only
  objects the master may write, a TxPDO only readable ones.
- 0x10F1 Error Settings (ETG.1020): sub 2, the sync error counter limit the DC cycle counts
  missed SYNC0 windows against (`sim_bus.ethercat.firmware`), held here, writable in PRE-OP
  only (the firmware takes it at the OP request); sub 1, the local error reaction, read-only.
- An object an assigned RxPDO maps (the controlword, the target torque): not written by SDO
  in SAFE-OP and OP, where the process data carries it.
- CANopen PDO communication parameters (COB-IDs, transmission types) do not exist on EtherCAT.

The same objects answer the SDO Information service (`object_list`, `object_description`,
`entry_description`), so what a tool browses is what an SDO reaches: the EDS's names, types
and access, PDO-mappable only where the ESI's PDOs carry the object.
"""

import struct

from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from protocol import cia301
from protocol import esi as esi_objects
from protocol import ethercat as ec
from protocol.dictionary import variable
from protocol.esi import EsiDevice
from protocol.pdo import split_mapping_entry
from sim_bus.device import Cia402Device, DeviceAccessError
from sim_bus.ethercat.mailbox import SdoAbort

_U8 = struct.Struct("<B")
_U16 = struct.Struct("<H")
_MASTER_WRITES = frozenset(("rw", "wo", "rww"))
_MASTER_READS = frozenset(("rw", "ro", "const", "rwr"))
_CANOPEN_PDO_COMMUNICATION = (range(0x1400, 0x1600), range(0x1800, 0x1A00))
_UNSIGNED8, _UNSIGNED16 = 0x0005, 0x0006  # CiA 301 data types
_ERROR_SETTINGS = esi_objects.error_settings()  # 0x10F1's names, types and access
# CiA 301 complex data types of the standard records, for their object descriptions
_RECORD_TYPES = ((range(ec.RXPDO_MAPPING_FIRST, ec.TXPDO_MAPPING_LAST + 1), 0x0021),
                 (range(0x1018, 0x1019), 0x0023))
_ACCESS = {"ro": ec.ENTRY_ACCESS_READ, "const": ec.ENTRY_ACCESS_READ,
           "wo": ec.ENTRY_ACCESS_WRITE}
_WRITE_PRE_OP = 0x0008  # object access: written in PRE-OP only


class CoeObjects:
    """The slave's object access for its CoE server (`sim_bus.ethercat.mailbox`)."""

    def __init__(self, device: Cia402Device, esi: EsiDevice):
        self.device = device
        self.esi = esi
        self.pdo_config_allowed = False  # PRE-OP only; the firmware sets it
        self.sm_types = tuple(sm.sm_type for sm in esi.sync_managers)
        self.assignable = {
            ec.RXPDO_ASSIGN: tuple(p.index for p in esi.rxpdos),
            ec.TXPDO_ASSIGN: tuple(p.index for p in esi.txpdos),
        }
        # per assignment object: its sub-indices 1..n and sub-index 0 (how many count)
        self._entries: dict[int, list[int]] = {}
        self._counts: dict[int, int] = {}
        self.sync_error_limit = esi_objects.SYNC_ERROR_COUNTER_LIMIT_DEFAULT  # 0x10F1:02
        self.fixed = frozenset(p.index for p in esi.rxpdos + esi.txpdos if p.fixed)
        self._rx_objects = frozenset((e.index, e.subindex) for p in esi.rxpdos for e in p.entries)
        self._tx_objects = frozenset((e.index, e.subindex) for p in esi.txpdos for e in p.entries)
        # the EtherCAT communication objects this class holds itself: name, entry type, count
        self._own = {ec.SM_COMMUNICATION_TYPE: ("Sync manager type", _UNSIGNED8,
                                                len(self.sm_types)),
                     ec.RXPDO_ASSIGN: ("RxPDO assign", _UNSIGNED16,
                                       len(self.assignable[ec.RXPDO_ASSIGN])),
                     ec.TXPDO_ASSIGN: ("TxPDO assign", _UNSIGNED16,
                                       len(self.assignable[ec.TXPDO_ASSIGN]))}
        self.reset()

    def reset(self) -> None:
        """The ESI's defaults: every PDO assigned to its sync manager, mapped as declared;
        the error settings at theirs."""
        self.sync_error_limit = esi_objects.SYNC_ERROR_COUNTER_LIMIT_DEFAULT
        for assign, pdos in self.assignable.items():
            sm = assign - ec.PDO_ASSIGN_BASE
            declared = self.esi.rxpdos + self.esi.txpdos
            defaults = [p.index for p in declared if p.index in pdos and p.sync_manager == sm]
            self._entries[assign] = defaults + [0] * (len(pdos) - len(defaults))
            self._counts[assign] = len(defaults)
        for pdo in self.esi.rxpdos + self.esi.txpdos:
            self.device.write(pdo.index, 0, 0)
            for k, entry in enumerate(pdo.entries, start=1):
                self.device.write(pdo.index, k, entry.mapping_entry)
            self.device.write(pdo.index, 0, len(pdo.entries))

    # --- the process data the assignment describes --------------------------------------------

    def assigned(self, assign: int) -> list[int]:
        """The PDOs assigned to a sync manager (0x1C12 / 0x1C13), in order."""
        return self._entries[assign][:self._counts[assign]]

    def assigned_entries(self, assign: int) -> list[int]:
        """The mapping entries of every PDO assigned to a sync manager, in order."""
        entries = []
        for pdo in self.assigned(assign):
            count = self.device.read(pdo, 0)
            entries.extend(self.device.read(pdo, k) for k in range(1, count + 1))
        return entries

    def _in_outputs(self, index: int, subindex: int) -> bool:
        """Whether an assigned RxPDO maps the object (what SM2's process data carries)."""
        return any(split_mapping_entry(entry)[:2] == (index, subindex)
                   for entry in self.assigned_entries(ec.RXPDO_ASSIGN))

    # --- ObjectAccess ---------------------------------------------------------------------

    def upload(self, index: int, subindex: int) -> bytes:
        if index == esi_objects.ERROR_SETTINGS:
            return self._error_setting(subindex).encode_raw(
                self.sync_error_limit if subindex == esi_objects.SYNC_ERROR_COUNTER_LIMIT
                else self._error_setting(subindex).default)
        if index == ec.SM_COMMUNICATION_TYPE:
            if subindex == 0:
                return _U8.pack(len(self.sm_types))
            if subindex <= len(self.sm_types):
                return _U8.pack(self.sm_types[subindex - 1])
            raise SdoAbort(cia301.SDO_ABORT_NO_SUBINDEX)
        if index in self.assignable:
            if subindex == 0:
                return _U8.pack(self._counts[index])
            if subindex <= len(self._entries[index]):
                return _U16.pack(self._entries[index][subindex - 1])
            raise SdoAbort(cia301.SDO_ABORT_NO_SUBINDEX)
        self._check_exists(index)
        try:
            return self.device.read_bytes(index, subindex)
        except DeviceAccessError as exc:
            raise SdoAbort(exc.abort_code) from None

    def download(self, index: int, subindex: int, data: bytes) -> None:
        if index == esi_objects.ERROR_SETTINGS:
            self._set_error_setting(subindex, data)
            return
        if index == ec.SM_COMMUNICATION_TYPE:
            raise SdoAbort(cia301.SDO_ABORT_WRITE_READ_ONLY)
        if index in self.assignable:
            self._assign(index, subindex, data)
            return
        self._check_exists(index)
        if _is_rx_mapping(index) or _is_tx_mapping(index):
            self._check_mapping(index, subindex, data)
        elif not self.pdo_config_allowed and self._in_outputs(index, subindex):
            # from SAFE-OP on the process data owns what its RxPDOs carry: a write here
            # would be overwritten by the next frame, and drives in the field refuse it
            # (SOEM's issues #567, #583); a master steers CiA 402 through its outputs
            raise SdoAbort(cia301.SDO_ABORT_WRONG_STATE)
        try:
            self.device.write_bytes(index, subindex, data)
        except DeviceAccessError as exc:
            raise SdoAbort(exc.abort_code) from None

    # --- SDO Information ------------------------------------------------------------------

    def object_list(self, kind: int) -> list[int]:
        dictionary = self.device.dictionary
        every = sorted({*self._own, esi_objects.ERROR_SETTINGS,
                        *(index for index in dictionary if not _canopen_communication(index))})
        if kind == ec.OD_LIST_ALL:
            return every
        if kind in (ec.OD_LIST_RXPDO_MAPPABLE, ec.OD_LIST_TXPDO_MAPPABLE):
            carried = self._rx_objects if kind == ec.OD_LIST_RXPDO_MAPPABLE else self._tx_objects
            return sorted({index for index, _ in carried if index in every})
        return []  # nothing is stored for backup or settings here

    def object_description(self, index: int) -> tuple[int, int, int, str]:
        if index == esi_objects.ERROR_SETTINGS:
            return 0, max(_ERROR_SETTINGS.subindices), ec.OBJECT_CODE_RECORD, _ERROR_SETTINGS.name
        if index in self._own:
            name, data_type, count = self._own[index]
            return data_type, count, ec.OBJECT_CODE_ARRAY, name
        obj = self._object(index)
        if isinstance(obj, ODVariable):
            return obj.data_type, 0, ec.OBJECT_CODE_VAR, obj.name
        highest = max(obj.subindices)
        if isinstance(obj, ODArray):
            entry = obj.subindices.get(1, obj.subindices[highest])
            return entry.data_type, highest, ec.OBJECT_CODE_ARRAY, obj.name
        data_type = next((kind for span, kind in _RECORD_TYPES if index in span), 0)
        return data_type, highest, ec.OBJECT_CODE_RECORD, obj.name

    def entry_description(self, index: int, subindex: int) -> tuple[int, int, int, str]:
        if index == esi_objects.ERROR_SETTINGS:
            var = self._error_setting(subindex)
            access = ec.ENTRY_ACCESS_READ | (_WRITE_PRE_OP if var.access_type == "rw" else 0)
            return var.data_type, len(var), access, var.name
        if index in self._own:
            name, data_type, count = self._own[index]
            if subindex > count:
                raise SdoAbort(cia301.SDO_ABORT_NO_SUBINDEX)
            write = 0 if index == ec.SM_COMMUNICATION_TYPE else _WRITE_PRE_OP
            if subindex == 0:
                return _UNSIGNED8, 8, ec.ENTRY_ACCESS_READ | write, "Number of entries"
            bits = 8 if data_type == _UNSIGNED8 else 16
            return data_type, bits, ec.ENTRY_ACCESS_READ | write, f"{name} {subindex}"
        obj = self._object(index)
        var = obj if isinstance(obj, ODVariable) and subindex == 0 else (
            None if isinstance(obj, ODVariable) else obj.subindices.get(subindex))
        if var is None:
            raise SdoAbort(cia301.SDO_ABORT_NO_SUBINDEX)
        access = _ACCESS.get(var.access_type, ec.ENTRY_ACCESS_READ | ec.ENTRY_ACCESS_WRITE)
        if access & ec.ENTRY_ACCESS_WRITE and (_is_rx_mapping(index) or _is_tx_mapping(index)):
            access = access & ~ec.ENTRY_ACCESS_WRITE | _WRITE_PRE_OP
        if (index, subindex) in self._rx_objects:
            access |= ec.ENTRY_ACCESS_RXPDO
        if (index, subindex) in self._tx_objects:
            access |= ec.ENTRY_ACCESS_TXPDO
        if var.data_type in ODVariable.STRUCT_TYPES:
            bits = len(var)
        else:  # a string or domain: as long as what it holds
            try:
                bits = 8 * len(self.device.read_bytes(index, subindex))
            except DeviceAccessError:
                bits = 0
        return var.data_type, bits, access, var.name

    def _error_setting(self, subindex: int) -> ODVariable:
        var = _ERROR_SETTINGS.subindices.get(subindex)
        if var is None:
            raise SdoAbort(cia301.SDO_ABORT_NO_SUBINDEX)
        return var

    def _set_error_setting(self, subindex: int, data: bytes) -> None:
        """0x10F1:02 in PRE-OP; the other entries are read-only."""
        var = self._error_setting(subindex)
        if var.access_type != "rw":
            raise SdoAbort(cia301.SDO_ABORT_WRITE_READ_ONLY)
        if not self.pdo_config_allowed:
            raise SdoAbort(cia301.SDO_ABORT_WRONG_STATE)
        if len(data) != len(var) // 8:
            raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
        self.sync_error_limit = var.decode_raw(data)

    def _object(self, index: int) -> ODVariable | ODArray | ODRecord:
        self._check_exists(index)
        obj = self.device.dictionary.get(index)
        if obj is None:
            raise SdoAbort(cia301.SDO_ABORT_NOT_IN_DICTIONARY)
        return obj

    def _check_exists(self, index: int) -> None:
        if _canopen_communication(index):
            raise SdoAbort(cia301.SDO_ABORT_NOT_IN_DICTIONARY)

    def _assign(self, index: int, subindex: int, data: bytes) -> None:
        if not self.pdo_config_allowed:
            raise SdoAbort(cia301.SDO_ABORT_WRONG_STATE)
        entries = self._entries[index]
        if subindex == 0:
            if len(data) != 1:
                raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
            (count,) = _U8.unpack(data)
            if count > len(entries) or not all(entries[:count]):
                raise SdoAbort(cia301.SDO_ABORT_VALUE_RANGE)
            self._counts[index] = count
            return
        if subindex > len(entries):
            raise SdoAbort(cia301.SDO_ABORT_NO_SUBINDEX)
        if self._counts[index]:
            raise SdoAbort(ec.SDO_ABORT_SUBINDEX_ZERO_NOT_ZERO)
        if len(data) != 2:
            raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
        (pdo,) = _U16.unpack(data)
        if pdo and pdo not in self.assignable[index]:
            raise SdoAbort(cia301.SDO_ABORT_VALUE_RANGE)
        entries[subindex - 1] = pdo

    def _check_mapping(self, index: int, subindex: int, data: bytes) -> None:
        if not self.pdo_config_allowed:
            raise SdoAbort(cia301.SDO_ABORT_WRONG_STATE)
        if index in self.fixed:
            raise SdoAbort(cia301.SDO_ABORT_WRITE_READ_ONLY)
        if subindex == 0:
            count = int.from_bytes(data, "little")
            try:
                complete = all(self.device.read(index, k) for k in range(1, count + 1))
            except DeviceAccessError as exc:
                raise SdoAbort(cia301.SDO_ABORT_PDO_LENGTH) from exc
            if not complete:
                raise SdoAbort(cia301.SDO_ABORT_VALUE_RANGE)  # entries missing
            return
        if self.device.read(index, 0):
            raise SdoAbort(ec.SDO_ABORT_SUBINDEX_ZERO_NOT_ZERO)
        if len(data) != 4:
            return  # the device names the length mismatch
        entry = int.from_bytes(data, "little")
        if not entry:
            return
        mapped, mapped_sub, _ = split_mapping_entry(entry)
        if (mapped, mapped_sub) not in self.esi.pdo_objects:
            raise SdoAbort(cia301.SDO_ABORT_NOT_MAPPABLE)  # the ESI does not offer it
        var = variable(self.device.dictionary, mapped, mapped_sub)
        allowed = _MASTER_WRITES if _is_rx_mapping(index) else _MASTER_READS
        if var is not None and var.access_type not in allowed:
            raise SdoAbort(cia301.SDO_ABORT_NOT_MAPPABLE)


def _is_rx_mapping(index: int) -> bool:
    return ec.RXPDO_MAPPING_FIRST <= index <= ec.RXPDO_MAPPING_LAST


def _is_tx_mapping(index: int) -> bool:
    return ec.TXPDO_MAPPING_FIRST <= index <= ec.TXPDO_MAPPING_LAST


def _canopen_communication(index: int) -> bool:
    return any(index in span for span in _CANOPEN_PDO_COMMUNICATION)
