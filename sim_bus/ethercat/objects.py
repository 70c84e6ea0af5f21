"""What the slave's CoE server reaches: the device's objects (its EDS dictionary) plus the
EtherCAT communication objects the ESI defines, with EtherCAT's rules on top.

- 0x1C00 sync manager types: read-only, from the ESI's sync managers.
- 0x1C12 / 0x1C13 PDO assignment of SM2 / SM3: the ESI's PDOs, changeable in PRE-OP only,
  sub-index 0 first set to 0 (ETG.1000.6).
- 0x1600.. / 0x1A00.. PDO mapping: held by the device (it validates the entries), changeable in
  PRE-OP only, sub-index 0 first set to 0, only objects the ESI's PDOs carry, an RxPDO only
  objects the master may write, a TxPDO only readable ones.
- CANopen PDO communication parameters (COB-IDs, transmission types) do not exist on EtherCAT.
"""

import struct

from protocol import cia301
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
        self.fixed = frozenset(p.index for p in esi.rxpdos + esi.txpdos if p.fixed)
        self.reset()

    def reset(self) -> None:
        """The ESI's defaults: every PDO assigned to its sync manager, mapped as declared."""
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

    # --- ObjectAccess ---------------------------------------------------------------------

    def upload(self, index: int, subindex: int) -> bytes:
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
        if index == ec.SM_COMMUNICATION_TYPE:
            raise SdoAbort(cia301.SDO_ABORT_WRITE_READ_ONLY)
        if index in self.assignable:
            self._assign(index, subindex, data)
            return
        self._check_exists(index)
        if _is_rx_mapping(index) or _is_tx_mapping(index):
            self._check_mapping(index, subindex, data)
        try:
            self.device.write_bytes(index, subindex, data)
        except DeviceAccessError as exc:
            raise SdoAbort(exc.abort_code) from None

    def _check_exists(self, index: int) -> None:
        if any(index in span for span in _CANOPEN_PDO_COMMUNICATION):
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
