"""A bus's process image worked on in one compiled call a cycle, whatever the number of joints.

A CAN bus's input image holds, per drive, the bytes of the TPDOs that answered this cycle's
SYNC (`driver.canopen_cycle.BusCycle`); its output image the bytes of the RPDOs going out. An
EtherCAT line's images are its slaves' process data one after the other
(`driver.drive_group.EthercatLine`).
Where each cyclic object sits is decided when the PDOs are mapped and given here as a layout
array: per joint and object, its offset in the image and a code, its size in bytes, negative
when signed, 0 when the drive does not have it. `decode` turns the inputs into a table of
samples in SI units (`driver.interface.SAMPLE_*` columns) with the sample guard and the
fault check on the way; `encode` checks motor currents against the drives' limits and writes
their targets. As numpy operations the same work took some fifteen calls a cycle, each about
a microsecond of interpreter overhead on arrays of one to a few dozen elements: more than the
scalar path it replaced for one joint (see the commit that brought it).
"""

import numba
import numpy as np

from driver.interface import (
    SAMPLE_JOINT_TORQUE,
    SAMPLE_MOTOR_CURRENT,
    SAMPLE_POSITION,
    SAMPLE_STATUSWORD,
    SAMPLE_T,
    SAMPLE_VELOCITY,
    Sample,
)
from protocol import cia301

JIT = {"cache": True, "error_model": "numpy", "nogil": True}
FAULT_MASK, FAULT_BITS = 0x004F, 0x0008  # CiA 402 statusword: fault (protocol.cia402's table)
# the inputs a drive's profile reads (`driver.profile.Profile.inputs`), in order
STATUSWORD, POSITION, VELOCITY, CURRENT, JOINT_TORQUE = range(5)
INPUTS = 5
OUTPUTS = 2  # controlword, target
# columns of a joint's scale row
RAD, AMPS, TORQUE, MAX_STEP = range(4)


def code(size: int, signed: bool) -> int:
    """An object's code in a layout: its size in bytes, negative when signed."""
    return -size if signed else size


@numba.njit(inline="always", **JIT)
def _read(image, at, kind):  # pragma: no cover - compiled
    size = abs(kind)
    value = np.int64(0)
    for b in range(size):
        value |= np.int64(image[at + b]) << (8 * b)
    if kind < 0 and value >= np.int64(1) << (8 * size - 1):
        value -= np.int64(1) << (8 * size)
    return value


@numba.njit(**JIT)
def decode(image, layout, scale, t, previous, cycles, table):  # pragma: no cover - compiled
    """The samples of every joint from `image` (uint8) into `table` (rows: joints), at time
    `t` (s); `layout` (joints x 2*INPUTS: offset, code per input); `scale` (joints x 4: rad
    per increment, A per feedback unit, N.m per torque unit, the guard's largest position step
    per cycle); `previous` the last positions (NaN: none), replaced by these (but the glitched
    joint's). Returns the first joint whose position jumped further than `cycles` periods
    allow, the first whose statusword shows a fault, the first whose torque sensor reading is
    saturated (-1: none)."""
    glitch = faulted = saturated = -1
    for j in range(table.shape[0]):
        statusword = _read(image, layout[j, 0], layout[j, 1])
        position = _read(image, layout[j, 2], layout[j, 3]) * scale[j, RAD]
        table[j, SAMPLE_T] = t
        table[j, SAMPLE_POSITION] = position
        table[j, SAMPLE_VELOCITY] = _read(image, layout[j, 4], layout[j, 5]) * scale[j, RAD]
        table[j, SAMPLE_MOTOR_CURRENT] = (_read(image, layout[j, 6], layout[j, 7])
                                          * scale[j, AMPS])
        table[j, SAMPLE_STATUSWORD] = statusword
        torque = np.nan
        if layout[j, 9] != 0:
            reading = _read(image, layout[j, 8], layout[j, 9])
            if reading >= cia301.INT32_MAX or reading <= cia301.INT32_MIN:
                if saturated < 0:
                    saturated = j
            else:
                torque = reading * scale[j, TORQUE]
        table[j, SAMPLE_JOINT_TORQUE] = torque
        if glitch < 0 and abs(position - previous[j]) > scale[j, MAX_STEP] * cycles:
            glitch = j  # its previous position kept, for the report
        else:
            previous[j] = position
        if faulted < 0 and statusword & FAULT_MASK == FAULT_BITS:
            faulted = j
    return glitch, faulted, saturated


@numba.njit(**JIT)
def encode(currents, limit, target_per_amp, controlword, layout, out):  # pragma: no cover
    """Every joint's controlword and target for motor `currents` (A) into `out` (uint8), at
    `layout` (joints x 2*OUTPUTS: offset, code); returns the first joint whose current its
    drive does not accept (beyond `limit`, or NaN), -1 when all are written (nothing is
    written otherwise)."""
    for j in range(currents.shape[0]):
        if not abs(currents[j]) <= limit[j]:
            return j
    for j in range(currents.shape[0]):
        target = np.int64(np.rint(currents[j] * target_per_amp[j]))
        for k, value in ((0, np.int64(controlword)), (1, target)):
            at, size = layout[j, 2 * k], abs(layout[j, 2 * k + 1])
            for b in range(size):
                out[at + b] = (value >> (8 * b)) & 0xFF
    return -1


def compile_ahead() -> None:
    """Load `decode` and `encode` now (compile them on a first run after an install): called
    before any drive is enabled, so a fresh install's compile (seconds) is not the first
    cycle's, which would leave the drives without SYNC past their watchdog (EMCY 0x8130 and a
    failed start, seen on the first run after a fresh compile). `decode` twice: a CAN bus's
    image is an array of its own, an EtherCAT line's the frame's bytes as they came (read-only
    to numba, a specialization of its own: loaded in the first cycle, it took a DC line's
    SYNC0 windows at the start)."""
    table = np.empty((1, len(Sample._fields)))
    for image in (np.zeros(2 * INPUTS, dtype=np.uint8),
                  np.frombuffer(bytes(2 * INPUTS), dtype=np.uint8)):
        decode(image, np.zeros((1, 2 * INPUTS), dtype=np.int64), np.ones((1, 4)), 0.0,
               np.full(1, np.nan), 1, table)
    encode(np.zeros(1), np.ones(1), np.ones(1), 0, np.zeros((1, 2 * OUTPUTS), dtype=np.int64),
           np.zeros(2 * OUTPUTS, dtype=np.uint8))
