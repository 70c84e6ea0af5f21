"""python-can's `udp_multicast` datagram, as pure functions: one CAN frame as a msgpack map of
`can.Message`'s fields (`can.interfaces.udp_multicast.utils.pack_message`). The lean
udp_multicast paths (the master's `driver.canopen_multicast`, the virtual drives'
`sim_bus.multicast`) read and write it without building a checked `can.Message` each frame,
so that python-can's own udp_multicast bus on the same group reads them as its own.
"""

import msgpack

DATAGRAM_MAX = 4096  # bytes: a CAN FD frame's map is well below


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
