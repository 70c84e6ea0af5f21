"""The udp_multicast datagram joined from its parts (`protocol.can_datagram.encode`, and
`encode_slices` for several frames cut from one buffer) is, byte for byte, what python-can's
own `pack_message` writes for the same frame: standard and extended ids at every msgpack
integer width, 0 to 8 data bytes, data and remote frames (the length of a remote frame is its
data's, as canopen sends it: none)."""

import itertools

import can
import pytest
from can.interfaces.udp_multicast.utils import pack_message

from protocol.can_datagram import decode, encode, encode_slices

IDS = (0x000, 0x001, 0x07F, 0x080, 0x0FF, 0x100, 0x182, 0x7FF,  # 11-bit
       0x800, 0xFFFF, 0x10000, 0x1FFFFFFF)  # 29-bit


def test_encode_writes_python_cans_datagram():
    for can_id, size, remote, stamp in itertools.product(IDS, range(9), (False, True),
                                                          (0.0, 1.5, 1_764_000_000.123456)):
        if remote and size:
            continue
        data = bytes(range(1, size + 1))
        message = can.Message(timestamp=stamp, arbitration_id=can_id, data=data,
                              is_extended_id=can_id > 0x7FF, is_remote_frame=remote)
        assert encode(can_id, data, stamp, remote) == pack_message(message), (can_id, size)
        if not remote:
            assert decode(encode(can_id, data, stamp)) == (can_id, data)


def test_frames_cut_from_one_buffer_are_python_cans_datagrams_with_one_stamp():
    data = bytes(range(1, 40))
    cuts = [(can_id, k, k + size) for k, (can_id, size) in
            enumerate(zip(IDS, itertools.cycle((8, 0, 3, 6))))]
    stamp = 1_764_000_000.25
    assert encode_slices(data, cuts, stamp) == [
        pack_message(can.Message(timestamp=stamp, arbitration_id=can_id,
                                 data=data[start:stop], is_extended_id=can_id > 0x7FF))
        for can_id, start, stop in cuts]


def test_decode_reads_python_cans_datagrams_in_place_and_anything_else_through_msgpack():
    for can_id, size, extended in itertools.product(IDS, range(9), (False, True)):
        if can_id > 0x7FF and not extended:
            continue
        data = bytes(range(10, 10 + size))
        message = can.Message(timestamp=1_764_000_000.5, arbitration_id=can_id, data=data,
                              is_extended_id=extended)
        assert decode(pack_message(message)) == (can_id, data), (can_id, size, extended)
    # canopen ignores remote and error frames
    remote = can.Message(arbitration_id=0x701, is_remote_frame=True, is_extended_id=False)
    error = can.Message(arbitration_id=0x0, is_error_frame=True, is_extended_id=False)
    assert decode(pack_message(remote)) is None
    assert decode(pack_message(error)) is None
    # a frame with a channel named is python-can's too (msgpack reads it)
    named = can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, channel="x")
    assert decode(pack_message(named)) == (0x181, b"\x01")
    good = encode(0x181, b"\x01\x02", 1.0)
    for bad in (good[:-1], good + b"\x00", b"\x00" + good[1:], b"not msgpack"):
        with pytest.raises(ValueError):
            decode(bad)
