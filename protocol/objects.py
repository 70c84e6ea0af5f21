"""Object indices and unit scaling of a CiA 402 drive's object dictionary.

The EDS is the source of truth for what a given drive has; this module names the objects the
code touches and converts their integer units to SI, in one place. CiA 301 communication
constants (COB-IDs, NMT, abort and emergency codes) are in `protocol.cia301`.
"""

import math

# CiA 301 communication objects
ERROR_REGISTER = 0x1001
SYNC_COB_ID = 0x1005  # the object holding the SYNC COB-ID, not the COB-ID itself
CYCLE_PERIOD_US = 0x1006
SYNC_WINDOW_US = 0x1007  # synchronous window length: TPDOs after a SYNC count only inside it
CONSUMER_HEARTBEAT = 0x1016  # sub n: node id << 16 | time in ms
PRODUCER_HEARTBEAT_MS = 0x1017
SYNC_COUNTER_OVERFLOW = 0x1019  # 0: SYNC without counter byte; 2..240: with it
RPDO_COMM = 0x1400
RPDO_MAP = 0x1600
TPDO_COMM = 0x1800
TPDO_MAP = 0x1A00
PDO_CHANNELS = 512  # 0x1400..0x15FF RPDOs, 0x1800..0x19FF TPDOs (CiA 301)


def is_pdo_mapping(index: int) -> bool:
    """A PDO mapping object (0x1600..0x17FF receive, 0x1A00..0x1BFF transmit)."""
    return RPDO_MAP <= index < RPDO_MAP + PDO_CHANNELS or (
        TPDO_MAP <= index < TPDO_MAP + PDO_CHANNELS)

# CiA 402 drive objects
ABORT_CONNECTION_OPTION = 0x6007  # reaction when the master is lost
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION = 0x605A
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
MAX_CURRENT = 0x6073
RATED_CURRENT = 0x6075
RATED_TORQUE = 0x6076
TORQUE_ACTUAL = 0x6077
CURRENT_ACTUAL = 0x6078
SOFTWARE_POSITION_LIMIT = 0x607D
ENCODER_RESOLUTION = 0x608F  # sub 1 increments per sub 2 revolutions
SUPPORTED_DRIVE_MODES = 0x6502

# Manufacturer objects of the elbow drive
TARGET_CURRENT = 0x2000
MOTOR_CURRENT_ACTUAL = 0x2001
JOINT_TORQUE_SENSOR = 0x2002
OVERCURRENT_TRIP = 0x2003
SYNC_ECHO = 0x2004  # counter byte of the SYNC a sample answers
FAULT_INJECTION = 0x2010  # virtual drive only

# Modes of operation (0x6060)
MODE_NONE = 0
MODE_CYCLIC_SYNC_TORQUE = 10
MODE_CYCLIC_SYNC_CURRENT = -1  # manufacturer specific: target 0x2000 in mA


def supports_mode(supported_drive_modes: int, mode: int) -> bool:
    """Whether 0x6502's bit for a standard mode is set (bit n-1 for mode n, CiA 402)."""
    return mode > 0 and bool(supported_drive_modes >> (mode - 1) & 1)


# Abort connection option codes (0x6007; 0 and others: no action)
ABORT_FAULT = 1
ABORT_DISABLE_VOLTAGE = 2
ABORT_QUICK_STOP = 3

# 19-bit absolute encoder on the joint (paper, section II): 2^19 increments per revolution.
# The stated default for a drive whose EDS has no encoder resolution 0x608F.
ENCODER_INCREMENTS_PER_REV = 2**19
INCREMENTS_PER_RAD = ENCODER_INCREMENTS_PER_REV / (2.0 * math.pi)

MILLI = 1000.0  # mA per A, mN.m per N.m, per mille


def position_to_increments(position: float,
                           increments_per_rad: float = INCREMENTS_PER_RAD) -> int:
    return int(round(position * increments_per_rad))


def increments_to_position(increments: int,
                           increments_per_rad: float = INCREMENTS_PER_RAD) -> float:
    return increments / increments_per_rad


def amps_to_milliamps(current: float) -> int:
    return int(round(current * MILLI))


def milliamps_to_amps(milliamps: int) -> float:
    return milliamps / MILLI
