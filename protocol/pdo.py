"""PDO contents as data, and their codecs.

A `PdoLayout` is one frame's mapped objects in wire order; its `struct.Struct` is built once
per layout (a cycle packs or unpacks several frames, so rebuilding formats per frame showed up
at the top of the lock-step profile). The elbow drive's default layout is below; which objects
a drive can map is its dictionary's business (`protocol.dictionary.mappable_object`).
"""

import struct
from dataclasses import dataclass
from functools import cached_property

import numpy as np

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

    @property
    def size(self) -> int:
        """Bytes on the wire."""
        return self.bits // 8

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.subindex:02X}"


def split_mapping_entry(entry: int) -> tuple[int, int, int]:
    """A mapping sub-index value as (index, subindex, bits)."""
    return entry >> 16 & 0xFFFF, entry >> 8 & 0xFF, entry & 0xFF


@dataclass(frozen=True)
class PdoLayout:
    """One PDO: the COB-ID base (added to the node id) and its mapped objects, in wire order."""

    cob_base: int
    objects: tuple[MappedObject, ...]

    def cob_id(self, node_id: int) -> int:
        return self.cob_base + node_id

    @cached_property
    def struct(self) -> struct.Struct:
        return struct.Struct("<" + "".join(_FORMAT[(o.bits, o.signed)] for o in self.objects))

    @property
    def size(self) -> int:
        return self.struct.size

    @cached_property
    def dtype(self) -> np.dtype:
        """The same layout as a packed numpy record (fields f0, f1, ... in wire order): a
        line's process image decodes every slave's PDO in one `np.frombuffer`."""
        return np.dtype([(f"f{k}", _DTYPE[(o.bits, o.signed)])
                         for k, o in enumerate(self.objects)])

    @property
    def indices(self) -> tuple[int, ...]:
        return tuple(o.index for o in self.objects)


_FORMAT = {(8, False): "B", (8, True): "b", (16, False): "H", (16, True): "h",
           (32, False): "I", (32, True): "i"}
_DTYPE = {(8, False): "u1", (8, True): "i1", (16, False): "<u2", (16, True): "<i2",
          (32, False): "<u4", (32, True): "<i4"}
CODEC_BITS = frozenset(bits for bits, _ in _FORMAT)  # object sizes a PDO can carry here

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

# The elbow drive's default layout (its EDS's mapping at boot): one RPDO with the command,
# three TPDOs with the sample, all on SYNC. The first TPDO echoes the SYNC's counter byte, so
# a master can tell this cycle's sample from a late or repeated one (CAN keeps one sender's
# frames in order: TPDO2 and 3 follow TPDO1).
RPDO_COMMAND = PdoLayout(0x200, (CONTROLWORD, TARGET_CURRENT))
TPDO_STATUS_POSITION = PdoLayout(0x180, (STATUSWORD, POSITION_ACTUAL, SYNC_ECHO))
TPDO_VELOCITY_CURRENT = PdoLayout(0x280, (VELOCITY_ACTUAL, MOTOR_CURRENT_ACTUAL))
TPDO_JOINT_TORQUE = PdoLayout(0x380, (JOINT_TORQUE_SENSOR,))

DEFAULT_RPDOS = (RPDO_COMMAND,)
DEFAULT_TPDOS = (TPDO_STATUS_POSITION, TPDO_VELOCITY_CURRENT, TPDO_JOINT_TORQUE)


def encode(layout: PdoLayout, values: dict[int, int]) -> bytes:
    """Pack values keyed by object index into the PDO's bytes."""
    return layout.struct.pack(*(values[o.index] for o in layout.objects))


def decode(layout: PdoLayout, data: bytes) -> dict[int, int]:
    """Unpack a PDO; a frame of the wrong length raises ValueError naming the COB base."""
    return dict(zip(layout.indices, unpack(layout, data), strict=True))


def unpack(layout: PdoLayout, data: bytes | bytearray) -> tuple[int, ...]:
    """The PDO's values in wire order; a frame of the wrong length raises ValueError."""
    codec = layout.struct
    if len(data) != codec.size:
        raise ValueError(
            f"PDO 0x{layout.cob_base:03X}: {len(data)} bytes received, {codec.size} expected")
    return codec.unpack(data)
