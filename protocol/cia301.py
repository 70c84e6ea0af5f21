"""CiA 301 (CANopen application layer) constants: COB-IDs, NMT, SDO abort codes, PDO
communication parameters, emergency codes. Declared once here for the master, the virtual
drive and the EtherCAT transport (CoE reuses the SDO abort and emergency codes)."""

from canopen.sdo.exceptions import SdoAbortedError

# Predefined connection set: COB-ID = base (+ node id where the service is per node)
NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080  # the SYNC frame (not to be confused with object 0x1005, which holds it)
EMCY_BASE = 0x080
TPDO_BASES = (0x180, 0x280, 0x380, 0x480)
RPDO_BASES = (0x200, 0x300, 0x400, 0x500)
SDO_TX_BASE = 0x580  # server -> client
SDO_RX_BASE = 0x600  # client -> server
HEARTBEAT_BASE = 0x700
COB_ID_MASK = 0x7FF  # 11-bit identifiers

# NMT commands (first byte of the NMT frame; second byte is the node id, 0 = all)
NMT_START = 0x01
NMT_STOP = 0x02
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82

# NMT states as heartbeat bytes
NMT_BOOT_UP = 0x00
NMT_STOPPED = 0x04
NMT_OPERATIONAL = 0x05
NMT_PRE_OPERATIONAL = 0x7F

# SYNC counter byte: 1..overflow value (0x1019, at most 240; 0 means no counter byte)
SYNC_COUNTER_MAX = 240

# PDO communication parameter (0x1400.., 0x1800..) sub 1: COB-ID and its flag bits
PDO_INVALID = 0x80000000  # bit 31: the PDO does not exist (disabled)
TRANSMISSION_SYNC = 1  # sub 2: sent on every SYNC
TRANSMISSION_ASYNC = 255  # sub 2: event-driven (manufacturer / profile specific)
PDO_MAX_BYTES = 8  # classic CAN frame

# Heartbeat consumer entry (0x1016 sub n): node id in bits 16..23, time in ms in bits 0..15
HEARTBEAT_CONSUMER_NODE_SHIFT = 16
HEARTBEAT_CONSUMER_TIME_MASK = 0xFFFF

# SDO abort codes (CiA 301 table 22); the same codes travel in EtherCAT CoE SDO aborts
SDO_ABORT_TOGGLE = 0x05030000  # toggle bit not alternated (segmented transfer)
SDO_ABORT_COMMAND = 0x05040001  # command specifier not valid or unknown
SDO_ABORT_UNSUPPORTED_ACCESS = 0x06010000
SDO_ABORT_READ_WRITE_ONLY = 0x06010001
SDO_ABORT_WRITE_READ_ONLY = 0x06010002
SDO_ABORT_NOT_IN_DICTIONARY = 0x06020000
SDO_ABORT_NOT_MAPPABLE = 0x06040041
SDO_ABORT_PDO_LENGTH = 0x06040042
SDO_ABORT_LENGTH_MISMATCH = 0x06070010
SDO_ABORT_NO_SUBINDEX = 0x06090011
SDO_ABORT_VALUE_RANGE = 0x06090030
SDO_ABORT_VALUE_TOO_HIGH = 0x06090031
SDO_ABORT_VALUE_TOO_LOW = 0x06090032
SDO_ABORT_WRONG_STATE = 0x08000022  # "because of the present device state"
# not in canopen's table: ETG.1000.6 (CoE) adds it for PDO mapping and assignment objects
_SDO_ABORT_EXTRA = {0x06010003: "Subindex cannot be written, SI0 must be 0 for write access"}


def sdo_abort_name(code: int) -> str:
    """'Value range of parameter exceeded (0x06090030)': the CiA 301 words for an SDO abort
    code (canopen's table, which a CANopen master shows too), the number where none is
    known."""
    words = SdoAbortedError.CODES.get(code) or _SDO_ABORT_EXTRA.get(code, "unknown abort code")
    return f"{words} (0x{code:08X})"

# Emergency error codes (CiA 301 table 21, CiA 402 annex)
EMCY_NO_ERROR = 0x0000
EMCY_OVERCURRENT = 0x2310  # continuous over-current, device output side
EMCY_HEARTBEAT = 0x8130  # life guard or heartbeat error
EMCY_SYNC_LENGTH = 0x8240  # unexpected SYNC data length
EMCY_POSITION_LIMIT = 0x8612  # positioning controller: reference limit

# Error register (0x1001) bits
ERROR_REGISTER_GENERIC = 0x01
ERROR_REGISTER_CURRENT = 0x02
ERROR_REGISTER_COMMUNICATION = 0x10

# Data-type limits a reading saturates at (a sensor pinned there is not a measurement)
INT32_MAX = 2**31 - 1
INT32_MIN = -(2**31)

# Data types (CiA 301 table 44) of the integers a PDO carries
SIGNED_TYPES = frozenset((0x02, 0x03, 0x04))  # INTEGER8, 16, 32
