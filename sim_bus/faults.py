"""Faults the virtual drive can be made to have, switchable at run time: from the command
line (`--inject-fault NAME@SECONDS`), by SDO (write the code to 0x2010) or from Python
(`Cia402Device.inject`). Each is what breaks on real hardware. The device acts out the
drive's own (sensors, power stage); the node exposing it acts out the communication's."""

from enum import IntEnum


class Fault(IntEnum):
    NONE = 0
    HEARTBEAT_STOPS = 1  # the heartbeat producer dies, PDOs go on
    SILENT = 2  # the drive vanishes from the bus (power, cable)
    TPDO_LATE = 3  # the next sample arrives 200 ms after its SYNC
    TPDO_TWICE = 4  # the next sample's frames are sent twice
    ENCODER_GLITCH = 5  # one position sample jumps by 5000 increments (0.06 rad)
    TORQUE_SENSOR_SATURATED = 6  # the torque reading sticks at the top of its range
    OVERCURRENT_TRIP = 7  # the power stage trips (EMCY 0x2310)
    BUS_FLOOD = 8  # another node floods the bus with high-priority frames for 0.5 s
    REBOOT = 9  # the drive resets and sends its boot-up message mid-run
    LEAVES_OP = 10  # EtherCAT: the slave drops from OP to SAFE-OP + ERROR (sync error 0x001A)
    # EtherCAT: the frame that runs this cycle is lost on its way back to the master (a bit
    # error on the return path): every slave took it, the master gets nothing
    FRAME_LOST = 11


TPDO_DELAY = 0.2  # s
ENCODER_JUMP = 5000  # increments
FLOOD_SECONDS = 0.5
FLOOD_COB_ID = 0x001  # above SYNC (0x080) in priority
SATURATED_READING = 2**31 - 1  # mN.m: the INT32 ceiling of 0x2002
