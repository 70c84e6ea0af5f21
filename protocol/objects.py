"""Object indices and unit scaling of the elbow drive's object dictionary.

The EDS (`elbow_drive.eds`) is the source of truth for the dictionary; this module names the
objects the code touches and converts their integer units to SI, in one place.
"""

import math

# CiA 301 communication objects
ERROR_REGISTER = 0x1001
SYNC_COB_ID = 0x1005
CYCLE_PERIOD_US = 0x1006
PRODUCER_HEARTBEAT_MS = 0x1017
RPDO_COMM = 0x1400
RPDO_MAP = 0x1600
TPDO_COMM = 0x1800
TPDO_MAP = 0x1A00

# CiA 402 drive objects
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
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
ENCODER_RESOLUTION = 0x608F

# Manufacturer objects
TARGET_CURRENT = 0x2000
MOTOR_CURRENT_ACTUAL = 0x2001
JOINT_TORQUE_SENSOR = 0x2002
OVERCURRENT_TRIP = 0x2003
SYNC_ECHO = 0x2004  # counter byte of the SYNC a sample answers
FAULT_INJECTION = 0x2010  # virtual drive only

# Modes of operation (0x6060)
MODE_NONE = 0
MODE_CYCLIC_SYNC_TORQUE = 10
MODE_CYCLIC_SYNC_CURRENT = -1

# EMCY error codes (CiA 301 / CiA 402)
EMCY_NO_ERROR = 0x0000
EMCY_OVERCURRENT = 0x2310
EMCY_POSITION_LIMIT = 0x8612
EMCY_SENSOR = 0x7300

ERROR_REGISTER_GENERIC = 0x01
ERROR_REGISTER_CURRENT = 0x02

# 19-bit absolute encoder on the joint (paper, section II): 2^19 increments per revolution.
ENCODER_INCREMENTS_PER_REV = 2**19
INCREMENTS_PER_RAD = ENCODER_INCREMENTS_PER_REV / (2.0 * math.pi)

MILLI = 1000.0


def position_to_increments(position: float) -> int:
    return int(round(position * INCREMENTS_PER_RAD))


def increments_to_position(increments: int) -> float:
    return increments / INCREMENTS_PER_RAD


def amps_to_milliamps(current: float) -> int:
    return int(round(current * MILLI))


def milliamps_to_amps(milliamps: int) -> float:
    return milliamps / MILLI
