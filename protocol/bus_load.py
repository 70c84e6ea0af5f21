"""How much of a fieldbus one control cycle uses: pure arithmetic over the PDO layout, the
bitrate and the period, so a robot file that cannot fit is refused before any bus is opened.

CAN (classic, 11-bit identifiers): a data frame of n bytes is 47 + 8 n bits on the wire before
bit stuffing (SOF, identifier, RTR, IDE, r0, DLC, data, CRC and its delimiter, ACK slot and
delimiter, EOF, and the 3-bit interframe space). Stuffing adds one bit after five equal bits in
the 34 + 8 n bits from SOF to the CRC: at worst (34 + 8 n - 1) / 4 more (Davis et al., "CAN
schedulability analysis: refuted, revisited and revised", 2007), about one in 16 on random
data. The load is counted on the unstuffed length and the budget is 90 % of the bus: the rest
covers typical stuffing (~5 %) and the acyclic traffic (EMCY, SDO). Worst-case stuffing is
reported beside it, because a bus that is near the budget can overrun on adverse data.

EtherCAT: one Ethernet frame per cycle carries every slave's process data in one logical
datagram (LRW); at 100 Mbit/s a frame of b bytes takes (b + preamble + interframe gap) x 8 bits.
"""

import math
from dataclasses import dataclass

CAN_FRAME_OVERHEAD_BITS = 47  # 11-bit identifier frame without data, interframe space included
CAN_STUFFED_REGION_BITS = 34  # SOF .. CRC without data: where stuffing can happen
CAN_CLASSIC_MAX_BITRATE = 1_000_000  # bit/s: the ceiling of classic CAN (ISO 11898-1)
CAN_BUDGET = 0.9  # share of the bus the cyclic traffic may take (unstuffed bits; see above)
ETHERCAT_BUDGET = 0.9  # the same margin for the acyclic mailbox traffic
HEARTBEAT_BYTES = 1  # NMT state
SYNC_BYTES = 1  # the CiA 301 counter byte

ETHERNET_OVERHEAD_BYTES = 8 + 14 + 4 + 12  # preamble+SFD, header, FCS, interframe gap
ETHERCAT_HEADER_BYTES = 2
ETHERCAT_DATAGRAM_OVERHEAD_BYTES = 10 + 2  # datagram header and working counter
ETHERNET_MIN_PAYLOAD_BYTES = 46
ETHERCAT_BITRATE = 100_000_000  # bit/s, 100BASE-TX


def can_frame_bits(data_bytes: int, worst_case_stuffing: bool = False) -> int:
    """Length in bits of one classic CAN data frame with `data_bytes` of data, unstuffed or
    with the most stuff bits any data can cause."""
    if not 0 <= data_bytes <= 8:
        raise ValueError(f"a classic CAN frame carries 0..8 data bytes, not {data_bytes}")
    bits = CAN_FRAME_OVERHEAD_BITS + 8 * data_bytes
    if worst_case_stuffing:
        bits += (CAN_STUFFED_REGION_BITS + 8 * data_bytes - 1) // 4
    return bits


@dataclass(frozen=True)
class BusLoad:
    """One bus's share taken by the cyclic traffic of its joints."""

    bus: str
    joints: int
    bits_per_cycle: float  # what each cycle sends (SYNC, PDOs)
    background_bits_per_s: float  # periodic traffic on its own clock (heartbeats)
    bitrate: int  # bit/s
    period_us: int
    budget: float  # the largest load accepted
    worst_case_bits_per_cycle: float  # with every frame maximally stuffed (CAN)
    worst_case_background_bits_per_s: float

    @property
    def load(self) -> float:
        """Fraction of the bus's time the traffic occupies (1.0 = saturated)."""
        return (self.bits_per_cycle / (self.period_us * 1e-6)
                + self.background_bits_per_s) / self.bitrate

    @property
    def worst_case_load(self) -> float:
        return (self.worst_case_bits_per_cycle / (self.period_us * 1e-6)
                + self.worst_case_background_bits_per_s) / self.bitrate

    @property
    def fits(self) -> bool:
        return self.load <= self.budget

    @property
    def fastest_period_us(self) -> int:
        """The shortest whole-microsecond period at which this traffic still fits."""
        spare = self.bitrate * self.budget - self.background_bits_per_s
        return math.ceil(self.bits_per_cycle / spare * 1e6)


def can_bus_load(bus: str, frame_bytes_per_joint: list[list[int]], bitrate: int,
                 period_us: int, heartbeat_ms: int, budget: float = CAN_BUDGET) -> BusLoad:
    """Load of one CAN bus: one SYNC per cycle, each joint's PDO frames (their data lengths)
    per cycle, and each node's heartbeat (and the master's) every `heartbeat_ms`."""
    if not 0 < bitrate <= CAN_CLASSIC_MAX_BITRATE:
        raise ValueError(f"bitrate {bitrate} bit/s: classic CAN runs at most "
                         f"{CAN_CLASSIC_MAX_BITRATE} bit/s")
    if period_us <= 0 or heartbeat_ms <= 0:
        raise ValueError("period and heartbeat time must be > 0")
    heartbeats_per_s = (len(frame_bytes_per_joint) + 1) * 1e3 / heartbeat_ms

    def cycle_bits(worst: bool) -> float:
        bits = float(can_frame_bits(SYNC_BYTES, worst))
        for frames in frame_bytes_per_joint:
            bits += sum(can_frame_bits(n, worst) for n in frames)
        return bits

    return BusLoad(bus, len(frame_bytes_per_joint), cycle_bits(False),
                   heartbeats_per_s * can_frame_bits(HEARTBEAT_BYTES), bitrate, period_us,
                   budget, cycle_bits(True),
                   heartbeats_per_s * can_frame_bits(HEARTBEAT_BYTES, True))


def ethercat_segment_load(bus: str, process_data_bytes_per_joint: list[int], period_us: int,
                          budget: float = ETHERCAT_BUDGET) -> BusLoad:
    """Load of one EtherCAT segment: every joint's process data in one frame per cycle."""
    data = sum(process_data_bytes_per_joint)
    payload = max(ETHERNET_MIN_PAYLOAD_BYTES,
                  ETHERCAT_HEADER_BYTES + ETHERCAT_DATAGRAM_OVERHEAD_BYTES + data)
    bits = 8.0 * (payload + ETHERNET_OVERHEAD_BYTES)
    return BusLoad(bus, len(process_data_bytes_per_joint), bits, 0.0, ETHERCAT_BITRATE,
                   period_us, budget, bits, 0.0)
