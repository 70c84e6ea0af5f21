"""The virtual drives' lean udp_multicast path (`sim_bus.multicast`) speaks python-can's
datagrams: a canopen master on python-can's own udp_multicast bus reads a drive served through
it (SDO, NMT, SYNC -> TPDOs) as it reads any other, and one thread receives for several buses."""

import math
import os
import random
import socket
import threading
import time

import can
import canopen
import pytest

from driver.clock import WallClock
from model.parameters import Payload, load_model
from protocol import cia301, objects
from protocol.bus_spec import parse_bus_spec
from sim_bus.canopen_node import CanOpenNode
from sim_bus.device import Cia402Device
from sim_bus.multicast import MulticastNetwork, MulticastReceiver
from sim_bus.rhythm import RHYTHM, Rhythm
from tests.conftest import udp_bus_spec, udp_port


@pytest.mark.real_time
def test_a_drive_served_through_it_answers_sdo_and_sync_on_two_buses_from_one_thread():
    specs = [udp_bus_spec(), udp_bus_spec()]
    networks = [MulticastNetwork(parse_bus_spec(spec)) for spec in specs]
    receiver = MulticastReceiver(networks)
    nodes = [CanOpenNode(network, node_id, Cia402Device(load_model(), Payload(),
                                                        node_id=node_id), clock=WallClock())
             for network, node_id in zip(networks, (3, 5), strict=True)]
    masters = []
    try:
        receiver.start()
        for spec, node in zip(specs, nodes, strict=True):
            master = canopen.Network()
            master.connect(**parse_bus_spec(spec))
            masters.append(master)
            remote = master.add_node(node.node_id, str(node.device.eds_path))
            booted = threading.Event()
            master.subscribe(cia301.HEARTBEAT_BASE + node.node_id,
                             lambda can_id, data, ts, booted=booted: data[0] == 0 and booted.set())
            node.boot()
            assert booted.wait(2), "no boot-up message through the lean path"
            # an SDO upload: request in through the receiver, answer out through sendto
            assert remote.sdo.upload(objects.STATUSWORD, 0) == node.device.read_bytes(
                objects.STATUSWORD, 0)
            tpdos: list[tuple[int, bytes]] = []
            got = threading.Event()

            def on_tpdo(can_id, data, ts, tpdos=tpdos, got=got):
                tpdos.append((can_id, bytes(data)))
                got.set()

            master.subscribe(cia301.TPDO_BASES[0] + node.node_id, on_tpdo)
            master.nmt.send_command(cia301.NMT_START)
            master.sync.transmit()
            assert got.wait(2), "no TPDO after the SYNC"
            assert node.sync_count == 1
            can_id, data = tpdos[0]
            assert can_id == cia301.TPDO_BASES[0] + node.node_id
            statusword = int.from_bytes(data[:2], "little")
            assert statusword == node.device.read(objects.STATUSWORD)
    finally:
        for master in masters:
            master.disconnect()
        receiver.stop()
        for node in nodes:
            node.close()
        for network in networks:
            network.disconnect()


def test_own_frames_do_not_come_back_to_the_network_that_sent_them():
    """Multicast loopback hands every frame back to its sender's socket: the kernel drops
    those from the network's own sending address, frames of other senders pass."""
    spec = udp_bus_spec()
    network = MulticastNetwork(parse_bus_spec(spec))
    receiver = MulticastReceiver([network])
    peer = canopen.Network()
    got: list[int] = []
    peer_frame = threading.Event()

    def on_frame(can_id, data, ts):
        got.append(can_id)
        if can_id == 0x124:
            peer_frame.set()

    network.subscribe(0x123, on_frame)
    network.subscribe(0x124, on_frame)
    try:
        receiver.start()
        peer.connect(**parse_bus_spec(spec))
        network.send_message(0x123, b"\x01")  # ours: looped back, dropped
        peer.send_message(0x124, b"\x02")  # sent after ours, so it arrives after it
        assert peer_frame.wait(2), "the peer's frame did not arrive"
        assert got == [0x124]
    finally:
        peer.disconnect()
        receiver.stop()
        network.disconnect()


def test_a_bus_does_not_hear_another_group_on_the_same_port():
    """Two buses on one port, groups of their own: a frame sent on the first reaches a
    python-can reader of the first group, and the second bus's socket never gets it
    (Linux's IP_MULTICAST_ALL default would queue it there too)."""
    port = udp_port()
    first, second = (f"udp_multicast:239.0.1.{n}:{port}"
                     for n in random.sample(range(1, 250), 2))
    witness = can.Bus(ignore_config=True, **parse_bus_spec(first))
    other = MulticastNetwork(parse_bus_spec(second))
    sender = MulticastNetwork(parse_bus_spec(first))
    try:
        sender.send_message(0x202, b"\x0f\x00")
        received = witness.recv(timeout=2.0)
        assert received is not None and received.arbitration_id == 0x202
        time.sleep(0.05)  # a datagram to the other group's socket would be queued by now
        with pytest.raises(BlockingIOError):
            other._socket.recv(4096)
    finally:
        sender.disconnect()
        other.disconnect()
        witness.shutdown()


def test_the_rhythm_expects_the_next_cycle_from_the_median_interval_of_the_last_ones():
    rhythm = Rhythm()
    period = 1e-3
    t = 100.0
    for k in range(RHYTHM):  # too few cycles yet to expect one
        rhythm.sync(t)
        rhythm.sync(t + 30e-6)  # another bus's SYNC of the same cycle
        assert rhythm.due == math.inf, k
        t += period
    rhythm.sync(t)
    assert rhythm.due == pytest.approx(t + period)
    # one late cycle (and the early one after it) does not move the median
    t += 1.6 * period
    rhythm.sync(t)
    t += 0.4 * period
    rhythm.sync(t)
    assert rhythm.due == pytest.approx(t + period)
    # a cycle that does not come (the master skipped a period) is expected on the same grid
    for k in range(1, RHYTHM + 1):
        rhythm.missed()
        assert rhythm.due == pytest.approx(t + (k + 1) * period), k
    rhythm.missed()  # RHYTHM periods without one: nothing is expected until a frame comes
    assert rhythm.due == math.inf
    t += (RHYTHM + 2) * period
    rhythm.sync(t)  # the next cycle's SYNC: expected again
    assert rhythm.due == pytest.approx(t + period)
    rhythm.missed()
    assert rhythm.due == pytest.approx(t + 2 * period)
    rhythm.sync(t + 2 * period)  # the one after a skipped period: the count starts again
    for _ in range(RHYTHM):
        rhythm.missed()
    assert rhythm.due < math.inf


def test_a_bus_on_a_descriptor_select_cannot_take_is_still_served():
    spec = udp_bus_spec()
    network = MulticastNetwork(parse_bus_spec(spec))
    high = 2000  # above FD_SETSIZE: the receiver sleeps in poll instead
    os.dup2(network._socket.fileno(), high)
    moved = socket.socket(fileno=high)
    network._socket.close()
    network._socket = moved
    got = threading.Event()
    network.subscribe(0x181, lambda can_id, data, ts: got.set())
    receiver = MulticastReceiver([network])
    receiver.start()
    try:
        with can.Bus(ignore_config=True, **parse_bus_spec(spec)) as other:
            other.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
            assert got.wait(2), "the frame was not received"
    finally:
        receiver.stop()
        network.disconnect()
