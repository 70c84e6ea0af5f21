"""EtherCAT wire format and constants (ETG.1000.4 data link layer, ETG.1000.6 application layer,
the ESC register map of the Beckhoff ET1100 datasheet), as pure data and functions.

Shared by the virtual slave controller (sim_bus/ethercat) and the pysoem master
(driver/ethercat_transport.py), so a register address or a status code has one home.
"""

import struct
from enum import IntEnum

ETHERTYPE = 0x88A4
ETHERNET_HEADER = struct.Struct("!6s6sH")  # destination, source, EtherType
ETHERNET_HEADER_SIZE = ETHERNET_HEADER.size
MIN_ETHERNET_FRAME = 60  # without FCS
SOURCE_MAC_OFFSET = 6
# the ESC sets the locally administered bit of the source address on the way back (ET1100)
SOURCE_MAC_PROCESSED_BIT = 0x02

# EtherCAT frame header: 11 bits length of the datagrams, 1 reserved, 4 bits type
FRAME_HEADER = struct.Struct("<H")
FRAME_HEADER_SIZE = FRAME_HEADER.size
FRAME_LENGTH_MASK = 0x07FF
FRAME_TYPE_SHIFT = 12
FRAME_TYPE_DLPDU = 1  # EtherCAT commands; the other types are not processed by an ESC

# Datagram header: command, index, address (ADP + ADO or 32-bit logical), length word, IRQ
DATAGRAM_HEADER = struct.Struct("<BBHHHH")
DATAGRAM_HEADER_SIZE = DATAGRAM_HEADER.size
DATAGRAM_LENGTH_MASK = 0x07FF
DATAGRAM_CIRCULATING = 0x4000
DATAGRAM_MORE_FOLLOWS = 0x8000
WKC = struct.Struct("<H")
WKC_SIZE = WKC.size


class Command(IntEnum):
    NOP = 0
    APRD = 1  # auto-increment physical read
    APWR = 2
    APRW = 3
    FPRD = 4  # configured address physical read
    FPWR = 5
    FPRW = 6
    BRD = 7  # broadcast read (the slaves' data ORed)
    BWR = 8
    BRW = 9
    LRD = 10  # logical read through the FMMUs
    LWR = 11
    LRW = 12
    ARMW = 13  # auto-increment read, multiple write
    FRMW = 14  # configured read, multiple write


class AlState(IntEnum):
    """AL control / AL status state values (bits 0-3); bit 4 is the error indicator in the
    status and the error acknowledge in the control."""

    NONE = 0x00
    INIT = 0x01
    PRE_OP = 0x02
    BOOT = 0x03
    SAFE_OP = 0x04
    OP = 0x08


AL_STATE_MASK = 0x0F
AL_ERROR = 0x10  # AL status: error indicator; AL control: error acknowledge

# AL status codes (ETG.1000.6 table "AL status codes"), by name for the master's reports
AL_STATUS_CODES = {
    0x0000: "no error",
    0x0001: "unspecified error",
    0x0002: "no memory",
    0x0011: "invalid requested state change",
    0x0012: "unknown requested state",
    0x0013: "bootstrap not supported",
    0x0014: "no valid firmware",
    0x0015: "invalid mailbox configuration (bootstrap)",
    0x0016: "invalid mailbox configuration",
    0x0017: "invalid sync manager configuration",
    0x0018: "no valid inputs available",
    0x0019: "no valid outputs",
    0x001A: "synchronization error",
    0x001B: "sync manager watchdog",
    0x001C: "invalid sync manager types",
    0x001D: "invalid output configuration",
    0x001E: "invalid input configuration",
    0x001F: "invalid watchdog configuration",
    0x0020: "slave needs cold start",
    0x0021: "slave needs INIT",
    0x0022: "slave needs PREOP",
    0x0023: "slave needs SAFEOP",
    0x0024: "invalid input mapping",
    0x0025: "invalid output mapping",
    0x0026: "inconsistent settings",
    0x0027: "freerun not supported",
    0x0028: "synchronization not supported",
    0x0029: "freerun needs 3 buffer mode",
    0x002A: "background watchdog",
    0x002B: "no valid inputs and outputs",
    0x002C: "fatal sync error",
    0x002D: "no sync error",
    0x0030: "invalid DC SYNC configuration",
    0x0031: "invalid DC latch configuration",
    0x0032: "PLL error",
    0x0033: "DC sync IO error",
    0x0034: "DC sync timeout error",
    0x0035: "DC invalid sync cycle time",
    0x0036: "DC sync0 cycle time",
    0x0037: "DC sync1 cycle time",
    0x0041: "MBX_AOE",
    0x0042: "MBX_EOE",
    0x0043: "MBX_COE",
    0x0044: "MBX_FOE",
    0x0045: "MBX_SOE",
    0x004F: "MBX_VOE",
    0x0050: "EEPROM no access",
    0x0051: "EEPROM error",
    0x0060: "slave restarted locally",
    0x0061: "device identification value updated",
    0x00F0: "application controller available",
}

AL_NO_ERROR = 0x0000
AL_INVALID_STATE_CHANGE = 0x0011
AL_UNKNOWN_STATE = 0x0012
AL_BOOTSTRAP_NOT_SUPPORTED = 0x0013
AL_INVALID_MAILBOX_CONFIGURATION = 0x0016
AL_INVALID_SM_CONFIGURATION = 0x0017
AL_SYNCHRONIZATION_ERROR = 0x001A
AL_SM_WATCHDOG = 0x001B
AL_INVALID_OUTPUT_CONFIGURATION = 0x001D
AL_INVALID_INPUT_CONFIGURATION = 0x001E
AL_SYNC_ERROR = 0x001A  # SYNC0 windows missed past the drive's sync error limit
AL_FATAL_SYNC_ERROR = 0x002C  # SYNC0 itself stopped coming
AL_INVALID_DC_SYNC_CONFIGURATION = 0x0030
AL_DC_INVALID_SYNC_CYCLE_TIME = 0x0035


def al_status_name(code: int) -> str:
    """'sync manager watchdog (0x001B)'; codes outside the table keep their number."""
    name = AL_STATUS_CODES.get(code)
    if name is None:
        name = "vendor specific" if code >= 0x8000 else "unknown AL status code"
    return f"{name} (0x{code:04X})"


def al_state_name(state: int) -> str:
    """'SAFE_OP', 'SAFE_OP + ERROR', or the number when it names no state."""
    try:
        name = AlState(state & AL_STATE_MASK).name
    except ValueError:
        name = f"0x{state & AL_STATE_MASK:X}"
    return name + (" + ERROR" if state & AL_ERROR else "")


# --- ESC registers (ET1100) -------------------------------------------------------------------
REG_TYPE = 0x0000
REG_REVISION = 0x0001
REG_BUILD = 0x0002
REG_FMMUS_SUPPORTED = 0x0004
REG_SMS_SUPPORTED = 0x0005
REG_RAM_SIZE = 0x0006  # KiB
REG_PORT_DESCRIPTOR = 0x0007
REG_FEATURES = 0x0008
REG_STATION_ADDRESS = 0x0010
REG_STATION_ALIAS = 0x0012
REG_DL_CONTROL = 0x0100
REG_DL_CONTROL_ALIAS = 0x0103  # bit 0: FPxx commands also match the station alias
REG_DL_STATUS = 0x0110
REG_AL_CONTROL = 0x0120
REG_AL_STATUS = 0x0130
REG_AL_STATUS_CODE = 0x0134
REG_PDI_CONTROL = 0x0140
REG_ESC_CONFIGURATION = 0x0141
REG_ECAT_EVENT_MASK = 0x0200
REG_AL_EVENT_REQUEST = 0x0220
REG_RX_ERROR_COUNTER = 0x0300  # port 0 invalid frame counter, then RX error counter, ...
REG_WATCHDOG_DIVIDER = 0x0400
REG_WATCHDOG_TIME_PDI = 0x0410
REG_WATCHDOG_TIME_PROCESS_DATA = 0x0420
REG_WATCHDOG_STATUS_PROCESS_DATA = 0x0440  # bit 0: 1 = not expired
REG_WATCHDOG_COUNTER_PROCESS_DATA = 0x0442
REG_EEPROM_CONFIGURATION = 0x0500  # bit 0: EEPROM offered to PDI, bit 1: force ECAT access
REG_EEPROM_PDI_ACCESS = 0x0501
REG_EEPROM_CONTROL = 0x0502  # control when written, status when read
REG_EEPROM_ADDRESS = 0x0504
REG_EEPROM_DATA = 0x0508
REG_FMMU0 = 0x0600
FMMU_SIZE = 16
REG_SM0 = 0x0800
SM_SIZE = 8
REG_DC_SYSTEM_TIME = 0x0910
REG_DC_SYNC_ACTIVATION = 0x0981
PROCESS_RAM_START = 0x1000
ADDRESS_SPACE = 0x10000

# watchdog time base: (divider + 2) x 40 ns; the ESC's reset values give 100 us x 1000 = 100 ms
WATCHDOG_DIVIDER_DEFAULT = 2498
WATCHDOG_TIME_DEFAULT = 1000
WATCHDOG_TICK_NS = 40

# EEPROM control/status register (0x0502)
EEPROM_WRITE_ENABLE = 0x0001
EEPROM_READ_8_BYTES = 0x0040
EEPROM_COMMAND_MASK = 0x0700
EEPROM_COMMAND_READ = 0x0100
EEPROM_COMMAND_WRITE = 0x0200
EEPROM_COMMAND_RELOAD = 0x0400
EEPROM_ERROR_ACKNOWLEDGE = 0x2000  # missing acknowledge / invalid command
EEPROM_ERROR_WRITE_ENABLE = 0x4000
EEPROM_BUSY = 0x8000

# DL status (0x0110): PDI operational, PDI watchdog reloaded, link on port 0/1, per port:
# loop open and communication established (10) or loop closed, no communication (01)
DL_STATUS_PDI_OPERATIONAL = 0x0001
DL_STATUS_PDI_WATCHDOG_OK = 0x0002
DL_STATUS_LINK_PORT0 = 0x0010
DL_STATUS_LINK_PORT1 = 0x0020
DL_STATUS_PORT0_OPEN = 0x0200
DL_STATUS_PORT1_OPEN = 0x0800
DL_STATUS_PORT1_CLOSED = 0x0400
DL_STATUS_PORT2_CLOSED = 0x1000
DL_STATUS_PORT3_CLOSED = 0x4000

# FMMU record (16 bytes): logical start, length, start bit, stop bit, physical start,
# physical start bit, type (bit 0 read, bit 1 write), activate
FMMU = struct.Struct("<IHBBHBBB3x")
FMMU_READ = 0x01
FMMU_WRITE = 0x02

# SyncManager record (8 bytes): physical start, length, control, status, activate, PDI control
SYNC_MANAGER = struct.Struct("<HHBBBB")
SM_CONTROL_MODE_MASK = 0x03
SM_MODE_BUFFERED = 0x00
SM_MODE_MAILBOX = 0x02
SM_CONTROL_DIRECTION_MASK = 0x0C
SM_DIRECTION_READ = 0x00  # the master reads (PDI writes): inputs, mailbox in
SM_DIRECTION_WRITE = 0x04  # the master writes: outputs, mailbox out
SM_CONTROL_WATCHDOG = 0x40  # a completed write retriggers the process data watchdog
SM_STATUS_MAILBOX_FULL = 0x08
SM_ACTIVATE_ENABLE = 0x01
SM_ACTIVATE_REPEAT = 0x02
SM_PDI_DEACTIVATE = 0x01
SM_PDI_REPEAT_ACK = 0x02
SM_OFFSET_CONTROL = 4
SM_OFFSET_STATUS = 5
SM_OFFSET_ACTIVATE = 6
SM_OFFSET_PDI_CONTROL = 7

# SyncManager types as in SII and CoE 0x1C00 (ETG.1000.6)
SM_TYPE_UNUSED = 0
SM_TYPE_MAILBOX_OUT = 1  # master -> slave
SM_TYPE_MAILBOX_IN = 2  # slave -> master
SM_TYPE_OUTPUTS = 3
SM_TYPE_INPUTS = 4

# --- mailbox (ETG.1000.4) and CoE (ETG.1000.6) --------------------------------------------------
MAILBOX_HEADER = struct.Struct("<HHBB")  # length, address, channel/priority, type | counter << 4
MAILBOX_HEADER_SIZE = MAILBOX_HEADER.size
MAILBOX_TYPE_ERROR = 0x00
MAILBOX_TYPE_COE = 0x03
MAILBOX_TYPE_MASK = 0x0F
MAILBOX_COUNTER_SHIFT = 4
MAILBOX_COUNTER_MASK = 0x07
# mailbox error reply: service 1, then the detail code
MAILBOX_ERROR_SERVICE = 0x0001
MAILBOX_ERROR_SYNTAX = 0x0001
MAILBOX_ERROR_UNSUPPORTED_PROTOCOL = 0x0002
MAILBOX_ERROR_SERVICE_NOT_SUPPORTED = 0x0004
MAILBOX_ERROR_INVALID_HEADER = 0x0005
MAILBOX_ERROR_SIZE_TOO_SHORT = 0x0006
MAILBOX_ERROR_INVALID_SIZE = 0x0008

# Emergency code class 0xA0xx: EtherCAT state machine transition error (ETG.1000.6); sent
# when the slave leaves OP under a powered drive (watchdog, or the master's request)
EMCY_ESM_TRANSITION = 0xA000

# mailbox protocols in SII word 0x1C
MAILBOX_PROTOCOL_COE = 0x0004

COE_HEADER = struct.Struct("<H")  # number (9 bits) | service << 12
COE_SERVICE_SHIFT = 12
COE_EMERGENCY = 0x01
COE_SDO_REQUEST = 0x02
COE_SDO_RESPONSE = 0x03
COE_SDO_INFORMATION = 0x08

# SDO Information service (ETG.1000.6 5.6.3): after the CoE header, opcode (bit 7: more
# fragments follow), a reserved byte, the fragments left; then the opcode's data
SDO_INFO_HEADER = struct.Struct("<BBH")
SDO_INFO_INCOMPLETE = 0x80
SDO_INFO_OPCODE_MASK = 0x7F
SDO_INFO_GET_OD_LIST_REQUEST = 0x01
SDO_INFO_GET_OD_LIST_RESPONSE = 0x02
SDO_INFO_GET_OBJECT_DESCRIPTION_REQUEST = 0x03
SDO_INFO_GET_OBJECT_DESCRIPTION_RESPONSE = 0x04
SDO_INFO_GET_ENTRY_DESCRIPTION_REQUEST = 0x05
SDO_INFO_GET_ENTRY_DESCRIPTION_RESPONSE = 0x06
SDO_INFO_ERROR = 0x07  # data: the SDO abort code
# Get OD List: which list (0: the length of each of lists 1-5)
OD_LIST_LENGTHS = 0
OD_LIST_ALL = 1
OD_LIST_RXPDO_MAPPABLE = 2
OD_LIST_TXPDO_MAPPABLE = 3
OD_LIST_BACKUP = 4
OD_LIST_SETTINGS = 5
OD_LISTS = (OD_LIST_ALL, OD_LIST_RXPDO_MAPPABLE, OD_LIST_TXPDO_MAPPABLE, OD_LIST_BACKUP,
            OD_LIST_SETTINGS)
# Get Object Description response: index, data type, max sub-index, object code; then name
OBJECT_DESCRIPTION = struct.Struct("<HHBB")
OBJECT_CODE_VAR = 0x07
OBJECT_CODE_ARRAY = 0x08
OBJECT_CODE_RECORD = 0x09
# Get Entry Description request: index, sub-index, value info; the response adds data type,
# bit length, object access, then (where value info asks: unit type, default, minimum,
# maximum) and the name
ENTRY_DESCRIPTION_REQUEST = struct.Struct("<HBB")
ENTRY_DESCRIPTION = struct.Struct("<HBBHHH")
ENTRY_VALUE_INFO_OPTIONAL = 0x78  # unit type, default, minimum, maximum: not given here
# object access bits of an entry description
ENTRY_ACCESS_READ = 0x0007  # in PRE-OP, SAFE-OP and OP
ENTRY_ACCESS_WRITE = 0x0038
ENTRY_ACCESS_RXPDO = 0x0040
ENTRY_ACCESS_TXPDO = 0x0080

# CoE details in the SII general category / ESI <CoE> attributes
COE_DETAILS_SDO = 0x01
COE_DETAILS_SDO_INFO = 0x02
COE_DETAILS_PDO_ASSIGN = 0x04
COE_DETAILS_PDO_CONFIG = 0x08
COE_DETAILS_COMPLETE_ACCESS = 0x20

# SDO header after the CoE header: command, index, subindex, 4 data bytes (CiA 301 layout)
SDO_HEADER = struct.Struct("<BHB")
SDO_HEADER_SIZE = SDO_HEADER.size
SDO_COMPLETE_ACCESS = 0x10
SDO_TOGGLE = 0x10
SDO_CCS_DOWNLOAD_SEGMENT = 0x00
SDO_CCS_DOWNLOAD = 0x20
SDO_CCS_UPLOAD = 0x40
SDO_CCS_UPLOAD_SEGMENT = 0x60
SDO_CCS_ABORT = 0x80
SDO_CCS_MASK = 0xE0
SDO_EXPEDITED = 0x02
SDO_SIZE_INDICATED = 0x01
SDO_LAST_SEGMENT = 0x01
SDO_SCS_UPLOAD_SEGMENT = 0x00
SDO_SCS_DOWNLOAD_SEGMENT = 0x20
SDO_SCS_UPLOAD = 0x40
SDO_SCS_DOWNLOAD = 0x60
SDO_SEGMENT_MIN_DATA = 7  # a segment carries at least 7 bytes on the wire (unused ones counted)

# CoE objects of the EtherCAT communication area (ETG.1000.6)
SM_COMMUNICATION_TYPE = 0x1C00
PDO_ASSIGN_BASE = 0x1C10  # 0x1C10 + SM number
RXPDO_ASSIGN = 0x1C12
TXPDO_ASSIGN = 0x1C13
# ETG.1000.6 abort code beside CiA 301's: an entry written while sub-index 0 is not 0
SDO_ABORT_SUBINDEX_ZERO_NOT_ZERO = 0x06010003
RXPDO_MAPPING_FIRST, RXPDO_MAPPING_LAST = 0x1600, 0x17FF
TXPDO_MAPPING_FIRST, TXPDO_MAPPING_LAST = 0x1A00, 0x1BFF

# --- SII EEPROM (ETG.2010) ----------------------------------------------------------------------
SII_WORD_PDI_CONTROL = 0x0000
SII_WORD_STATION_ALIAS = 0x0004
SII_WORD_CHECKSUM = 0x0007
SII_CONFIG_BYTES = 14  # words 0-6, covered by the CRC-8 in word 7
SII_WORD_VENDOR_ID = 0x0008
SII_WORD_PRODUCT_CODE = 0x000A
SII_WORD_REVISION = 0x000C
SII_WORD_SERIAL = 0x000E
SII_WORD_STANDARD_RX_MAILBOX = 0x0018  # offset, size (master -> slave)
SII_WORD_STANDARD_TX_MAILBOX = 0x001A  # offset, size (slave -> master)
SII_WORD_MAILBOX_PROTOCOL = 0x001C
SII_WORD_SIZE = 0x003E  # EEPROM size in KiBit - 1
SII_WORD_VERSION = 0x003F
SII_FIRST_CATEGORY = 0x0040
SII_CATEGORY_STRINGS = 10
SII_CATEGORY_GENERAL = 30
SII_CATEGORY_FMMU = 40
SII_CATEGORY_SYNC_MANAGER = 41
SII_CATEGORY_TXPDO = 50
SII_CATEGORY_RXPDO = 51
SII_CATEGORY_END = 0xFFFF
SII_FMMU_OUTPUTS = 1
SII_FMMU_INPUTS = 2
SII_ERASED_WORD = 0xFFFF


def datagram_spans(frame: bytes | bytearray | memoryview, length: int | None = None,
                   start: int = ETHERNET_HEADER_SIZE) -> list[tuple[int, int, int, int]] | None:
    """(command, header offset, data offset, data length) of each datagram of the EtherCAT
    frame that begins at `start` in `frame` (the first `length` bytes are valid), or None when
    it is not a frame an ESC processes: another EtherType, another frame type, lengths running
    past the frame, a datagram cut short. Offsets are into `frame`. Never raises."""
    if length is None:
        length = len(frame)
    if length < start + FRAME_HEADER_SIZE or start < ETHERNET_HEADER_SIZE:
        return None
    if frame[start - 2] != ETHERTYPE >> 8 or frame[start - 1] != ETHERTYPE & 0xFF:
        return None
    word = frame[start] | frame[start + 1] << 8
    if word >> FRAME_TYPE_SHIFT != FRAME_TYPE_DLPDU:
        return None
    end = start + FRAME_HEADER_SIZE + (word & FRAME_LENGTH_MASK)
    if end > length:
        return None
    spans = []
    header = start + FRAME_HEADER_SIZE
    while True:
        data = header + DATAGRAM_HEADER_SIZE
        if data + WKC_SIZE > end:
            return None
        length_word = frame[header + 6] | frame[header + 7] << 8
        size = length_word & DATAGRAM_LENGTH_MASK
        if data + size + WKC_SIZE > end:
            return None
        spans.append((frame[header], header, data, size))
        if not length_word & DATAGRAM_MORE_FOLLOWS:
            return spans
        header = data + size + WKC_SIZE


def encode_frame(datagrams: list[tuple[int, int, int, bytes]],
                 source: bytes = b"\x01\x01\x01\x01\x01\x01") -> bytes:
    """An Ethernet frame carrying (command, index, address, data) datagrams with working
    counter 0, padded to the Ethernet minimum: what a master sends."""
    body = bytearray()
    for n, (command, index, address, data) in enumerate(datagrams):
        more = DATAGRAM_MORE_FOLLOWS if n < len(datagrams) - 1 else 0
        body += DATAGRAM_HEADER.pack(command, index, address & 0xFFFF, address >> 16,
                                     len(data) | more, 0)
        body += data + bytes(WKC_SIZE)
    frame = (ETHERNET_HEADER.pack(b"\xff" * 6, source, ETHERTYPE)
             + FRAME_HEADER.pack(len(body) | FRAME_TYPE_DLPDU << FRAME_TYPE_SHIFT) + body)
    return frame + bytes(max(0, MIN_ETHERNET_FRAME - len(frame)))


def datagram_result(frame: bytes, span: tuple[int, int, int, int]) -> tuple[bytes, int]:
    """(data, working counter) of one datagram (a `datagram_spans` entry) of a frame."""
    _, _, data, size = span
    return bytes(frame[data:data + size]), WKC.unpack_from(frame, data + size)[0]


def crc8_sii(data: bytes) -> int:
    """CRC-8 of the SII configuration area (polynomial x^8 + x^2 + x + 1, initial 0xFF), as
    the ESC checks it at power-on (ETG.2010)."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x07) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


def watchdog_seconds(divider: int, time: int) -> float:
    """The process data watchdog period set by registers 0x0400 and 0x0420 (0 = off)."""
    return (divider + 2) * WATCHDOG_TICK_NS * 1e-9 * time
