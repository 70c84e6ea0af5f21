"""The master's lean udp_multicast path (`driver.canopen_multicast`): frames a network sent
itself are not handed back to it, frames from any other socket are, stamped with the kernel's
receive time; python-can reads what it sends; one thread receives for every bus. (The master
driving a sim-bus process on it: tests/test_two_processes.py, test_standard_drives.py.)"""

import threading
import time

import can
import canopen
import pytest

from driver import canopen_multicast
from driver.canopen_multicast import MulticastNetwork
from driver.canopen_transport import open_network
from protocol.bus_spec import parse_bus_spec
from tests.conftest import udp_bus_spec

TPDO1 = 0x181


def _receivers() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "multicast-receiver"]


def test_own_frames_are_dropped_and_another_sockets_arrive_with_the_kernels_stamp():
    spec = udp_bus_spec()
    network = open_network(spec)
    other = can.Bus(ignore_config=True, **parse_bus_spec(spec))
    try:
        assert isinstance(network, MulticastNetwork)
        delivered: list[tuple[int, bytes, float]] = []
        arrived = threading.Event()

        def record(can_id: int, data: bytes, timestamp: float) -> None:
            delivered.append((can_id, bytes(data), timestamp))
            arrived.set()

        network.subscribe(TPDO1, record)
        before = time.time()
        network.send_message(TPDO1, b"\x01\x02")  # ours: looped back by the host, dropped
        other.send(can.Message(arbitration_id=TPDO1, data=b"\x07", is_extended_id=False))
        assert arrived.wait(2), "a frame from another socket was not delivered"
        after = time.time()
        time.sleep(0.05)  # anything still on its way (nothing should be) gets its chance
        assert [(can_id, data) for can_id, data, _ in delivered] == [(TPDO1, b"\x07")]
        assert before <= delivered[0][2] <= after
        # counted by the network itself, as BusWatch reads it: the one frame, its stamp
        assert (network.frames, network.last_stamp) == (1, delivered[0][2])
        # python-can reads the master's datagram as its own kind
        seen = other.recv(1)
        while seen is not None and bytes(seen.data) == b"\x07":  # its own, looped back
            seen = other.recv(1)
        assert seen is not None and (seen.arbitration_id, bytes(seen.data)) == (TPDO1,
                                                                                b"\x01\x02")
    finally:
        other.shutdown()
        network.disconnect()


def test_one_thread_receives_for_every_bus_and_leaves_with_the_last():
    specs = [udp_bus_spec(), udp_bus_spec()]
    networks = [open_network(spec) for spec in specs]
    try:
        assert len(_receivers()) == 1
        # each bus's traffic reaches its own network only
        got = [threading.Event(), threading.Event()]
        for network, event in zip(networks, got, strict=True):
            network.subscribe(TPDO1, lambda can_id, data, ts, event=event: event.set())
        with can.Bus(ignore_config=True, **parse_bus_spec(specs[1])) as other:
            other.send(can.Message(arbitration_id=TPDO1, data=b"\x01", is_extended_id=False))
            assert got[1].wait(2)
        assert not got[0].is_set()
    finally:
        for network in networks:
            network.disconnect()
    assert _receivers() == []


def test_other_interfaces_keep_python_cans_path():
    network = open_network("virtual:lean-path-test")
    try:
        assert not isinstance(network, MulticastNetwork)
        assert isinstance(network, canopen.Network) and network.notifier is not None
    finally:
        network.disconnect()


@pytest.mark.real_time
def test_the_cycle_reads_the_buses_itself_and_the_thread_takes_them_back_when_it_stops(
        monkeypatch):
    # the receive thread takes the buses back after STALL without the cycle reading: long
    # enough here that a busy host's pause between the test's steps does not pass it
    monkeypatch.setattr(canopen_multicast, "STALL", 0.3)
    spec = udp_bus_spec()
    network = open_network(spec)
    other = can.Bus(ignore_config=True, **parse_bus_spec(spec))
    try:
        readers: list[str] = []
        arrived = threading.Event()

        def on_frame(can_id: int, data: bytes, timestamp: float) -> None:
            readers.append(threading.current_thread().name)
            arrived.set()

        network.subscribe(TPDO1, on_frame)
        # the cycle waits for its frame: its own thread handles it, the receiver sleeps
        network.receive_until(lambda: True, 0.0)  # the cycle takes the buses
        other.send(can.Message(arbitration_id=TPDO1, data=b"\x01", is_extended_id=False))
        network.receive_until(arrived.is_set, 2.0)
        assert readers == [threading.current_thread().name]
        # nothing arrives: the wait ends at its timeout
        started = time.monotonic()
        network.receive_until(lambda: False, 0.02)
        assert time.monotonic() - started >= 0.02
        # the cycle stopped reading: the receive thread reads again (after STALL)
        arrived.clear()
        other.send(can.Message(arbitration_id=TPDO1, data=b"\x02", is_extended_id=False))
        assert arrived.wait(2), "the receive thread did not take the bus back"
        assert readers[1:] == ["multicast-receiver"]
    finally:
        other.shutdown()
        network.disconnect()
    assert _receivers() == []
