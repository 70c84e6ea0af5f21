"""The default PDO layout of the elbow drive, as data, and the codecs for it.

The master writes this layout into the drive by SDO (0x1400/0x1600, 0x1800/0x1A00); the drive
reads its own dictionary back to build the same codecs, so what crosses the wire is defined once.
"""

import struct
from dataclasses import dataclass

from protocol import objects as od


@dataclass(frozen=True)
class MappedObject:
    index: int
    subindex: int
    bits: int
    signed: bool

    @property
    def mapping_entry(self) -> int:
        """The 32-bit value stored in a 0x16xx/0x1Axx mapping sub-index."""
        return (self.index << 16) | (self.subindex << 8) | self.bits


@dataclass(frozen=True)
class PdoLayout:
    """One PDO: the COB-ID base (added to the node id) and its mapped objects, in wire order."""

    cob_base: int
    objects: tuple[MappedObject, ...]

    def cob_id(self, node_id: int) -> int:
        return self.cob_base + node_id

    @property
    def struct(self) -> struct.Struct:
        return struct.Struct("<" + "".join(_FORMAT[(o.bits, o.signed)] for o in self.objects))


_FORMAT = {(8, False): "B", (8, True): "b", (16, False): "H", (16, True): "h",
           (32, False): "I", (32, True): "i"}

CONTROLWORD = MappedObject(od.CONTROLWORD, 0, 16, False)
TARGET_CURRENT = MappedObject(od.TARGET_CURRENT, 0, 32, True)
TARGET_TORQUE = MappedObject(od.TARGET_TORQUE, 0, 16, True)
STATUSWORD = MappedObject(od.STATUSWORD, 0, 16, False)
POSITION_ACTUAL = MappedObject(od.POSITION_ACTUAL, 0, 32, True)
VELOCITY_ACTUAL = MappedObject(od.VELOCITY_ACTUAL, 0, 32, True)
MOTOR_CURRENT_ACTUAL = MappedObject(od.MOTOR_CURRENT_ACTUAL, 0, 32, True)
JOINT_TORQUE_SENSOR = MappedObject(od.JOINT_TORQUE_SENSOR, 0, 32, True)
TORQUE_ACTUAL = MappedObject(od.TORQUE_ACTUAL, 0, 16, True)
SYNC_ECHO = MappedObject(od.SYNC_ECHO, 0, 8, False)
CURRENT_ACTUAL = MappedObject(od.CURRENT_ACTUAL, 0, 16, True)

KNOWN_OBJECTS = {(o.index, o.subindex): o for o in (
    CONTROLWORD, TARGET_CURRENT, TARGET_TORQUE, STATUSWORD, POSITION_ACTUAL, VELOCITY_ACTUAL,
    MOTOR_CURRENT_ACTUAL, JOINT_TORQUE_SENSOR, TORQUE_ACTUAL, CURRENT_ACTUAL, SYNC_ECHO)}

# Default layout: one RPDO with the command, three TPDOs with the sample (all on SYNC). The
# first TPDO echoes the SYNC's counter byte, so a master can tell this cycle's sample from a
# late or repeated one (CAN keeps one sender's frames in order: TPDO2 and 3 follow TPDO1).
RPDO_COMMAND = PdoLayout(0x200, (CONTROLWORD, TARGET_CURRENT))
TPDO_STATUS_POSITION = PdoLayout(0x180, (STATUSWORD, POSITION_ACTUAL, SYNC_ECHO))
TPDO_VELOCITY_CURRENT = PdoLayout(0x280, (VELOCITY_ACTUAL, MOTOR_CURRENT_ACTUAL))
TPDO_JOINT_TORQUE = PdoLayout(0x380, (JOINT_TORQUE_SENSOR,))

DEFAULT_RPDOS = (RPDO_COMMAND,)
DEFAULT_TPDOS = (TPDO_STATUS_POSITION, TPDO_VELOCITY_CURRENT, TPDO_JOINT_TORQUE)
TRANSMISSION_SYNC = 1
TRANSMISSION_ASYNC = 255


def object_from_mapping_entry(entry: int) -> MappedObject:
    """Decode a 0x16xx/0x1Axx entry; the drive refuses objects it cannot map."""
    key = (entry >> 16, (entry >> 8) & 0xFF)
    bits = entry & 0xFF
    known = KNOWN_OBJECTS.get(key)
    if known is None or known.bits != bits:
        raise ValueError(f"object 0x{key[0]:04X}:{key[1]:02X} with {bits} bits is not mappable")
    return known


def encode(layout: PdoLayout, values: dict[int, int]) -> bytes:
    """Pack values keyed by object index into the PDO's bytes."""
    return layout.struct.pack(*(values[o.index] for o in layout.objects))


def decode(layout: PdoLayout, data: bytes) -> dict[int, int]:
    """Unpack a PDO; a frame of the wrong length raises ValueError naming the COB base."""
    expected = layout.struct.size
    if len(data) != expected:
        raise ValueError(
            f"PDO 0x{layout.cob_base:03X}: {len(data)} bytes received, {expected} expected")
    return dict(zip((o.index for o in layout.objects), layout.struct.unpack(data), strict=True))
