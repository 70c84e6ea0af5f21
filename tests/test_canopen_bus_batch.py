"""A CAN bus's batch (`sim_bus.canopen_node._BusSync`) against the device it batches: the
drives of test_line_physics's script (enabling, a window fault and its reset, a quick stop,
scheduled faults, a mode change by SDO, a payload change, drifting friction) behind CANopen
nodes on one embedded bus, driven by RPDOs and SYNCs, must send in every cycle the TPDOs that
the same devices cycled by `Cia402Device.cycle()` alone give, and end in the same state; an
object read between an RPDO and the SYNC sees the RPDO's value, as on a drive that applies
it on receipt."""

import struct

import numpy as np
import pytest

from driver.clock import DriveClock
from model.parameters import Payload
from protocol import cia301, objects
from sim_bus.canopen_node import CanOpenNode
from sim_bus.embedded import LinkedNetwork
from tests.test_line_physics import CYCLES, OUTPUTS, _drives, _observed, _outputs

# RPDO 1 of each drive: controlword, target torque, target current (CiA 301 mapping entries)
RPDO_MAPPING = (0x60400010, 0x60710010, 0x20000020)
RPDO = struct.Struct("<Hhi")


def _linked() -> tuple[LinkedNetwork, LinkedNetwork]:
    drives, master = LinkedNetwork(), LinkedNetwork()
    drives.peers.append(master)
    master.peers.append(drives)
    return drives, master


# the script's drives on the bus: all four, or one alone (joint 3: an over-current trip and
# its reset; joint 1: drifting friction and an encoder glitch), a lone drive being a batch too
@pytest.mark.parametrize("on_bus", [(0, 1, 2, 3), (3,), (1,)])
def test_a_bus_of_drives_answers_every_sync_as_its_devices_alone_would(on_bus):
    reference, batched = ([devices[j] for j in on_bus] for devices in (_drives(), _drives()))
    drives, master = _linked()
    clock = DriveClock()
    nodes = [CanOpenNode(drives, j + 1, device, clock=clock, silence_timeout=None)
             for j, device in enumerate(batched)]
    emergencies = ([], [])
    for side, devices in enumerate((reference, batched)):
        for j, device in enumerate(devices):
            device.add_emergency_handler(
                lambda code, register, j=j, side=side: emergencies[side].append((j, code)))
            # the COB-IDs of node j + 1 (the devices were made for no node: $NODEID 0)
            for comm, bases in ((objects.RPDO_COMM, cia301.RPDO_BASES),
                                (objects.TPDO_COMM, cia301.TPDO_BASES)):
                for n, base in enumerate(bases):
                    if (comm + n, 1) in device.values:
                        invalid = device.read(comm + n, 1) & cia301.PDO_INVALID
                        device.write(comm + n, 1, invalid | base + j + 1)
            device.write(objects.RPDO_MAP, 0, 0)
            for k, entry in enumerate(RPDO_MAPPING, start=1):
                device.write(objects.RPDO_MAP, k, entry)
            device.write(objects.RPDO_MAP, 0, len(RPDO_MAPPING))
    own_cycles = [0]  # the cycles the devices ran themselves, not the batch
    for device in batched:
        cycle = device.cycle
        device.cycle = lambda counter=0, cycle=cycle: (
            own_cycles.__setitem__(0, own_cycles[0] + 1), cycle(counter))
    tpdos: list[tuple[int, bytes]] = []
    for node in nodes:
        node.boot()
        for base in cia301.TPDO_BASES:
            master.subscribe(base + node.node_id,
                             lambda can_id, data, ts: tpdos.append((can_id, bytes(data))))
    master.send_message(cia301.NMT_COB_ID, bytes([cia301.NMT_START, 0]))
    assert all(len(node._rpdos) == 1 and len(node._tpdos) == 3 for node in nodes)
    for k in range(CYCLES):
        if k == 500:  # a mode change by SDO, a payload picked up
            for devices in (reference, batched):
                script = dict(zip(on_bus, devices, strict=True))
                if 1 in script:
                    script[1].write(objects.MODES_OF_OPERATION, 0,
                                    objects.MODE_CYCLIC_SYNC_CURRENT)
                if 3 in script:
                    script[3].plant.set_payload(Payload(mass=2.0, x=0.0, y=0.05))
        expected = []
        for j, device in enumerate(reference):
            outputs = _outputs(on_bus[j], k)
            device.write_outputs(OUTPUTS, outputs)
            master.send_message(cia301.RPDO_BASES[0] + j + 1, RPDO.pack(*outputs))
            if k % 97 == 0:  # looked at before the SYNC: the RPDO is in force
                assert batched[j].read(objects.TARGET_TORQUE) == outputs[1], (k, j)
        for j, device in enumerate(reference):
            device.cycle()
            expected += [(pdo.cob_id, pdo.pack(*pdo.values_of(device.values)))
                         for pdo in nodes[j]._tpdos]
        tpdos.clear()
        master.send_message(cia301.SYNC_COB_ID, b"")
        assert tpdos == expected, k
        if 1300 <= k < 1700 and k % 100:
            continue  # unobserved, the batch's cycles pile up before they are written back
        for j in range(len(on_bus)):
            assert np.allclose(batched[j].plant.state, reference[j].plant.state, rtol=0,
                               atol=1e-12), (k, j)
            assert _observed(batched[j]) == _observed(reference[j]), (k, j)
        assert emergencies[1] == emergencies[0], k
    # the script's events happened on CAN too, and the batch ran the steady cycles
    codes = {code for _, code in emergencies[0]}
    assert {code for j, code in ((0, 0x8612), (3, 0x2310)) if j in on_bus} <= codes, codes
    assert all(node.sync_count == CYCLES for node in nodes)
    # the devices ran the cycles with events (the enabling and the script's faults: more
    # than ten of the four drives'), the batch every other one
    assert (10 if len(on_bus) > 1 else 0) < own_cycles[0] < 100, own_cycles
    line = nodes[0]._bus.line
    assert line.devices == batched
    for node in nodes:
        node.close()
    assert not hasattr(drives, "_virtual_drives_sync")


def test_frames_sent_as_slices_arrive_as_frames_sent_one_by_one():
    """`LinkedNetwork.send_slices` (a node's TPDOs, a bus's RPDOs) hands the peer's
    subscribers, and a peer that is only a tap (`notify`), the same frames in the same order
    as a `send_message` per frame, counted the same, with one stamp."""

    class Tap:
        def __init__(self):
            self.frames = []

        def notify(self, can_id, data, timestamp):
            self.frames.append((can_id, bytes(data), timestamp))

    data = bytes(range(20))
    frames = ((0x181, 0, 8), (0x281, 8, 14), (0x381, 14, 20), (0x181, 3, 5))
    received = []
    for send in ("slices", "one by one"):
        drives, master = _linked()
        tap = Tap()
        drives.peers.append(tap)
        got = []
        for cob_id in (0x181, 0x281, 0x381):
            master.subscribe(cob_id, lambda can_id, frame, stamp, got=got: got.append(
                (can_id, frame, stamp)))
        if send == "slices":
            drives.send_slices(data, frames)
        else:
            for cob_id, start, stop in frames:
                drives.send_message(cob_id, data[start:stop])
        assert master.frames == len(frames) and master.last_stamp == got[-1][2]
        assert [frame[:2] for frame in got] == [frame[:2] for frame in tap.frames]
        assert all(type(frame) is bytes for _, frame, _ in got)
        received.append(got)
    assert [frame[:2] for frame in received[0]] == [frame[:2] for frame in received[1]] == [
        (cob_id, data[start:stop]) for cob_id, start, stop in frames]
    assert len({stamp for *_, stamp in received[0]}) == 1  # they left together
