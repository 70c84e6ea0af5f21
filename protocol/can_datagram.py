"""python-can's `udp_multicast` datagram, as pure functions: one CAN frame as a msgpack map of
`can.Message`'s fields (`can.interfaces.udp_multicast.utils.pack_message`). The lean
udp_multicast paths (the master's `driver.canopen_multicast`, the virtual drives'
`sim_bus.multicast`) read and write it without building a checked `can.Message` each frame,
so that python-can's own udp_multicast bus on the same group reads them as its own.
"""

import ctypes
import ipaddress
import socket
import struct
from collections.abc import Sequence

import msgpack

DATAGRAM_MAX = 4096  # bytes: a CAN FD frame's map is well below
# TTL of the lean paths' frames: the bus crosses processes on one machine (README), and python-
# can's 1 sends each frame out of the host's interface as well as looping it back; that
# transmit doubled the cost of a send (talos_arm across processes: a SYNC with its three
# TPDOs took the drive 127 us median at 1, 63 us at 0). A bus spec's own hop_limit wins
HOP_LIMIT = 0
SO_ATTACH_FILTER = 26  # Linux: a classic BPF program run on each datagram the socket queues
_BPF = struct.Struct("HBBI")  # struct sock_filter: code, jump if true, jump if false, k
_SKF_NET_OFF = -0x100000  # BPF offset base of the IP header (0: the UDP header on a UDP socket)


def _packed(can_id: int, data: bytes, timestamp: float, remote: bool) -> bytes:
    """msgpack's own packing of the frame's map (python-can's `pack_message`)."""
    return msgpack.packb({
        "timestamp": timestamp, "arbitration_id": can_id, "is_extended_id": can_id > 0x7FF,
        "is_remote_frame": remote, "is_error_frame": False, "channel": None,
        "dlc": len(data), "data": data, "is_fd": False, "bitrate_switch": False,
        "error_state_indicator": False}, use_bin_type=True)


def _key(name: str) -> bytes:
    return msgpack.packb(name)


# the map's fixed parts as msgpack writes them (a fixmap of 11, the keys as fixstr, False,
# None); `encode` joins them with the frame's own values
_HEAD = b"\x8b" + _key("timestamp") + b"\xcb"  # float 64
_DOUBLE = struct.Struct(">d")
_ID = _key("arbitration_id")
_FLAGS = {(extended, remote): _key("is_extended_id") + msgpack.packb(extended)
          + _key("is_remote_frame") + msgpack.packb(remote) + _key("is_error_frame")
          + b"\xc2" + _key("channel") + b"\xc0" + _key("dlc")
          for extended in (False, True) for remote in (False, True)}
_DATA = _key("data") + b"\xc4"  # bin 8
_TAIL = _key("is_fd") + b"\xc2" + _key("bitrate_switch") + b"\xc2" + _key(
    "error_state_indicator") + b"\xc2"
_UINT16 = struct.Struct(">BH")
_UINT32 = struct.Struct(">BI")


def _id_part(can_id: int) -> bytes:
    """The arbitration id's key and its value as msgpack's smallest unsigned form."""
    if can_id < 0x80:
        number = bytes((can_id,))  # positive fixint
    elif can_id < 0x100:
        number = bytes((0xCC, can_id))  # uint 8
    elif can_id < 0x10000:
        number = _UINT16.pack(0xCD, can_id)
    else:
        number = _UINT32.pack(0xCE, can_id)
    return _ID + number


_STANDARD_IDS = tuple(_id_part(can_id) for can_id in range(0x800))  # 11-bit, made once
# from the flags to the data's bin header, per (extended, remote, data length)
_MIDDLE = {(extended, remote, size): _FLAGS[(extended, remote)] + bytes((size,)) + _DATA
           + bytes((size,)) for extended, remote in _FLAGS for size in range(0x80)}


def encode(can_id: int, data: bytes, timestamp: float, remote: bool = False) -> bytes:
    """A classic CAN frame (11-bit id up to 0x7FF, 29-bit above, as canopen sends it) sent
    at `timestamp` (s since the epoch), as python-can's `pack_message` writes it: msgpack's
    bytes for that map, joined from its fixed parts (a frame is sent each time a drive or
    the master sends, dozens a millisecond; building the map and packing it took about
    three times as long)."""
    size = len(data)
    if size > 0x7F or not 0 <= can_id <= 0xFFFFFFFF:
        return _packed(can_id, data, timestamp, remote)
    extended = can_id > 0x7FF
    return b"".join((_HEAD, _DOUBLE.pack(timestamp),
                     _id_part(can_id) if extended else _STANDARD_IDS[can_id],
                     _MIDDLE[(extended, bool(remote), size)], data, _TAIL))


def encode_slices(data: bytes, frames: Sequence[tuple[int, int, int]],
                  timestamp: float) -> list[bytes]:
    """The datagrams of several classic data frames sent together at `timestamp`, each
    `(can_id, start, stop)` a slice of `data` (a drive's TPDOs cut from one packed buffer, a
    master's RPDOs from its output image): `encode`'s, the stamp packed once."""
    stamp = _HEAD + _DOUBLE.pack(timestamp)
    out = []
    for can_id, start, stop in frames:
        size = stop - start
        if size > 0x7F or not 0 <= can_id <= 0x7FF:
            out.append(encode(can_id, data[start:stop], timestamp))
            continue
        out.append(b"".join((stamp, _STANDARD_IDS[can_id], _MIDDLE[(False, False, size)],
                             data[start:stop], _TAIL)))
    return out


# where `decode`'s fast path finds the parts of a classic data frame's map
_ID_AT = len(_HEAD) + _DOUBLE.size
_ID_VALUE_AT = _ID_AT + len(_ID)
_DATA_FLAGS = {extended: _FLAGS[(extended, False)] for extended in (False, True)}


def decode(datagram: bytes) -> tuple[int, bytes] | None:
    """(CAN id, data) of a data frame; None for an error or remote frame (canopen ignores
    both). Raises ValueError for a datagram that is not python-can's.

    A classic data frame's map, as `encode` and python-can write it, is read in place (its
    fixed parts compared, the id and the data sliced out): each side of a bus decodes every
    frame it receives, dozens a millisecond, and msgpack's dict of eleven keys took about
    twice as long. Any other datagram is read by msgpack."""
    if datagram.startswith(_HEAD) and datagram.startswith(_ID, _ID_AT):
        at = _ID_VALUE_AT
        kind = datagram[at]
        if kind < 0x80:  # positive fixint
            can_id, at = kind, at + 1
        elif kind == 0xCC:
            can_id, at = datagram[at + 1], at + 2
        elif kind == 0xCD:
            can_id, at = _UINT16.unpack_from(datagram, at)[1], at + 3
        elif kind == 0xCE:
            can_id, at = _UINT32.unpack_from(datagram, at)[1], at + 5
        else:
            can_id = -1
        flags = _DATA_FLAGS[can_id > 0x7FF]
        if can_id >= 0 and datagram.startswith(flags, at):
            at += len(flags) + 1  # the dlc, a positive fixint in a classic frame
            size_at = at + len(_DATA)
            if (datagram[at - 1] < 0x80 and datagram.startswith(_DATA, at)
                    and len(datagram) == size_at + 1 + datagram[size_at] + len(_TAIL)
                    and datagram.endswith(_TAIL)):
                return can_id, datagram[size_at + 1:size_at + 1 + datagram[size_at]]
    try:
        frame = msgpack.unpackb(datagram, raw=False)
        if frame["is_error_frame"] or frame["is_remote_frame"]:
            return None
        return frame["arbitration_id"], frame["data"]
    except (ValueError, KeyError, TypeError, msgpack.UnpackException) as exc:
        raise ValueError(f"not a python-can datagram: {exc}") from exc


def sender_options(family: socket.AddressFamily,
                   hop_limit: int = HOP_LIMIT) -> list[tuple[int, int, int]]:
    """The `setsockopt` arguments of a socket that sends to the group: its frames looped back
    to this host's receivers (the other processes on the bus), `hop_limit` its TTL."""
    if family == socket.AF_INET6:
        return [(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, hop_limit),
                (socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_LOOP, 1)]
    return [(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, hop_limit),
            (socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)]


# Linux's <linux/in.h>, <linux/in6.h> (Python's socket module has neither name)
IP_MULTICAST_ALL = 49
IPV6_MULTICAST_ALL = 29


def receiver_options(family: socket.AddressFamily) -> list[tuple[int, int, int]]:
    """The `setsockopt` arguments of a socket that receives one bus: only its own group's
    datagrams. Linux's default (IP_MULTICAST_ALL on) hands a socket bound to the group's
    port every group's datagrams to that port that any socket of the host joined: buses
    on one port and several groups would each read all the others' frames, and take
    their SYNCs and PDOs for their own where node ids repeat."""
    if family == socket.AF_INET6:
        return [(socket.IPPROTO_IPV6, IPV6_MULTICAST_ALL, 0)]
    return [(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)]


def own_frames_fprog(address: str, port: int) -> tuple[ctypes.Array, bytes]:
    """`own_frames_filter` as SO_ATTACH_FILTER takes it: (the program's buffer, to be kept
    alive until the option is set, and the struct sock_fprog pointing at it)."""
    program = own_frames_filter(address, port)
    buffer = ctypes.create_string_buffer(program, len(program))
    return buffer, struct.pack("HL", len(program) // _BPF.size, ctypes.addressof(buffer))


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
