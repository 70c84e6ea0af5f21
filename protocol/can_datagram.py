"""python-can's `udp_multicast` datagram, as pure functions: one CAN frame as a msgpack map of
`can.Message`'s fields (`can.interfaces.udp_multicast.utils.pack_message`). The lean
udp_multicast paths (the master's `driver.canopen_multicast`, the virtual drives'
`sim_bus.multicast`) read and write it without building a checked `can.Message` each frame,
so that python-can's own udp_multicast bus on the same group reads them as its own.
"""

import ipaddress
import struct

import msgpack

DATAGRAM_MAX = 4096  # bytes: a CAN FD frame's map is well below
_BPF = struct.Struct("HBBI")  # struct sock_filter: code, jump if true, jump if false, k
_SKF_NET_OFF = -0x100000  # BPF offset base of the IP header (0: the UDP header on a UDP socket)


def encode(can_id: int, data: bytes, timestamp: float, remote: bool = False) -> bytes:
    """A classic CAN frame (11-bit id up to 0x7FF, 29-bit above, as canopen sends it) sent
    at `timestamp` (s since the epoch), as python-can's `pack_message` writes it."""
    return msgpack.packb({
        "timestamp": timestamp, "arbitration_id": can_id, "is_extended_id": can_id > 0x7FF,
        "is_remote_frame": remote, "is_error_frame": False, "channel": None,
        "dlc": len(data), "data": data, "is_fd": False, "bitrate_switch": False,
        "error_state_indicator": False}, use_bin_type=True)


def decode(datagram: bytes) -> tuple[int, bytes] | None:
    """(CAN id, data) of a data frame; None for an error or remote frame (canopen ignores
    both). Raises ValueError for a datagram that is not python-can's."""
    try:
        frame = msgpack.unpackb(datagram, raw=False)
        if frame["is_error_frame"] or frame["is_remote_frame"]:
            return None
        return frame["arbitration_id"], frame["data"]
    except (ValueError, KeyError, TypeError, msgpack.UnpackException) as exc:
        raise ValueError(f"not a python-can datagram: {exc}") from exc


def own_frames_filter(address: str, port: int) -> bytes:
    """A classic BPF program (Linux SO_ATTACH_FILTER on a UDP socket) that drops the
    datagrams sent from `address`:`port` (IPv4) and keeps every other: a sender's own frames,
    which multicast loopback hands back to its receiving socket, dropped by the kernel before
    they are queued, so they cost the receiving thread no wake-up. Source port from the UDP
    header, source address from the IP header."""
    return b"".join(_BPF.pack(*insn) for insn in (
        (0x28, 0, 0, 0),  # ldh [0]: the UDP source port
        (0x15, 0, 3, port),  # jeq #port, else keep
        (0x20, 0, 0, (_SKF_NET_OFF + 12) & 0xFFFFFFFF),  # ld [ip + 12]: the source address
        (0x15, 0, 1, int(ipaddress.IPv4Address(address))),  # jeq #address, else keep
        (0x06, 0, 0, 0),  # ret 0: drop
        (0x06, 0, 0, 0xFFFFFFFF)))  # ret: keep all of it
