"""Bringing a CANopen drive up: SDO access with errors that name the object, NMT reset and
boot-up, and the PDO mapping planned within what the drive's EDS allows, written by SDO and
read back."""

from collections.abc import Sequence

import can
import canopen
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from driver.canopen_cycle import PlannedPdo
from driver.interface import DriveError, ProfileError, SdoRefused
from protocol import cia301, objects
from protocol.dictionary import default_value, has, variable
from protocol.pdo import MappedObject, PdoLayout

_BUS_ERRORS = (SdoAbortedError, SdoCommunicationError, can.CanError, OSError)


class SdoAccess:
    """Expedited and segmented SDO through canopen, typed by the drive's EDS."""

    def __init__(self, node: canopen.RemoteNode, name: str):
        self.node = node
        self.name = name

    def _variable(self, index: int, subindex: int):
        var = variable(self.node.object_dictionary, index, subindex)
        if var is None:
            raise DriveError(f"{self.name}: 0x{index:04X}:{subindex:02X} is not in the drive's "
                             "EDS")
        return var

    def read(self, index: int, subindex: int = 0) -> int:
        var = self._variable(index, subindex)
        try:
            return var.decode_raw(self.node.sdo.upload(index, subindex))
        except _BUS_ERRORS as exc:
            raise DriveError(f"{self.name}: SDO read 0x{index:04X}:{subindex:02X} failed: "
                             f"{exc}") from exc

    def write(self, index: int, subindex: int, value: int) -> None:
        var = self._variable(index, subindex)
        try:
            self.node.sdo.download(index, subindex, var.encode_raw(value))
        except SdoAbortedError as exc:
            raise SdoRefused(f"{self.name}: SDO write 0x{index:04X}:{subindex:02X} = {value} "
                             f"aborted: {cia301.sdo_abort_name(exc.code)}", exc.code) from exc
        except _BUS_ERRORS as exc:
            raise DriveError(f"{self.name}: SDO write 0x{index:04X}:{subindex:02X} = {value} "
                             f"failed: {exc}") from exc


def plan_pdos(dictionary: ObjectDictionary, node_id: int, mapped: Sequence[MappedObject],
              receive: bool, echo: MappedObject | None, name: str) -> list[PlannedPdo]:
    """Pack `mapped` in order into the drive's PDO channels (RPDOs if `receive`, else TPDOs),
    at most 8 bytes and the EDS's number of mapping entries each; the SYNC counter echo, when
    given, ends the first one. ProfileError when the EDS has too few channels."""
    comm, mapping = ((objects.RPDO_COMM, objects.RPDO_MAP) if receive
                     else (objects.TPDO_COMM, objects.TPDO_MAP))
    channels = [n for n in range(objects.PDO_CHANNELS)
                if has(dictionary, comm + n, 1) and has(dictionary, mapping + n, 0)]
    plan: list[PlannedPdo] = []
    position = 0
    for n in channels:
        if position >= len(mapped) and not (echo is not None and not plan):
            break
        entries = len(dictionary[mapping + n]) - 1
        reserve = echo.size if echo is not None and not plan else 0
        taken: list[MappedObject] = []
        size = 0
        while (position < len(mapped) and len(taken) < entries - (1 if reserve else 0)
               and size + mapped[position].size + reserve <= cia301.PDO_MAX_BYTES):
            size += mapped[position].size
            taken.append(mapped[position])
            position += 1
        start = position - len(taken)
        if reserve:
            taken.append(echo)
        if taken:
            plan.append(PlannedPdo(n, _cob_id(dictionary, comm + n, n, node_id, receive),
                                   PdoLayout(0, tuple(taken)), start, position,
                                   echo=bool(reserve)))
    if position < len(mapped):
        left = ", ".join(str(o) for o in mapped[position:])
        kind = "receive" if receive else "transmit"
        raise ProfileError(f"{name}: the EDS's {len(channels)} {kind} PDOs cannot carry "
                           f"{left} as well")
    return plan


def _cob_id(dictionary: ObjectDictionary, comm: int, n: int, node_id: int,
            receive: bool) -> int:
    """The EDS's COB-ID for channel n, else the predefined connection set's."""
    value = default_value(variable(dictionary, comm, 1)) & cia301.COB_ID_MASK
    if value:
        return value
    bases = cia301.RPDO_BASES if receive else cia301.TPDO_BASES
    if n >= len(bases):
        raise ProfileError(f"PDO 0x{comm:04X} has no COB-ID in the EDS")
    return bases[n] + node_id


def write_pdos(sdo: SdoAccess, plan: Sequence[PlannedPdo], receive: bool,
               transmission: int) -> None:
    """Write the plan into the drive (CiA 301 order: invalidate, set the type, clear the
    mapping, write entries, set the count, validate), disable every other channel, and read
    each mapping back: a drive that stored something else is refused."""
    dictionary = sdo.node.object_dictionary
    comm, mapping = ((objects.RPDO_COMM, objects.RPDO_MAP) if receive
                     else (objects.TPDO_COMM, objects.TPDO_MAP))
    used = {p.channel for p in plan}
    for pdo in plan:
        c, m = comm + pdo.channel, mapping + pdo.channel
        sdo.write(c, 1, pdo.cob_id | cia301.PDO_INVALID)
        sdo.write(c, 2, transmission)
        sdo.write(m, 0, 0)
        for k, obj in enumerate(pdo.layout.objects, start=1):
            sdo.write(m, k, obj.mapping_entry)
        sdo.write(m, 0, len(pdo.layout.objects))
        sdo.write(c, 1, pdo.cob_id)
        stored = [sdo.read(m, k) for k in range(1, sdo.read(m, 0) + 1)]
        wanted = [obj.mapping_entry for obj in pdo.layout.objects]
        cob_id = sdo.read(c, 1)
        if stored != wanted or cob_id & (cia301.PDO_INVALID | cia301.COB_ID_MASK) != pdo.cob_id:
            raise DriveError(f"{sdo.name}: PDO 0x{c:04X} read back as COB-ID 0x{cob_id:X}, "
                             f"mapping {[hex(e) for e in stored]}; wrote 0x{pdo.cob_id:X}, "
                             f"{[hex(e) for e in wanted]}")
    for n in range(objects.PDO_CHANNELS):
        if n not in used and has(dictionary, comm + n, 1):
            cob_id = sdo.read(comm + n, 1)
            if not cob_id & cia301.PDO_INVALID:
                sdo.write(comm + n, 1, cob_id | cia301.PDO_INVALID)
