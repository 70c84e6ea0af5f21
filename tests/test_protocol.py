import canopen
import pytest

from protocol import eds_path, objects
from protocol import pdo as pdo_layout
from protocol.bus_spec import BusSpecError, parse_bus_spec
from protocol.dictionary import mappable_object

ELBOW_OBJECTS = [v for v in vars(pdo_layout).values() if isinstance(v, pdo_layout.MappedObject)]


def test_eds_holds_every_mapped_object_with_matching_size():
    od = canopen.import_od(str(eds_path()), 2)
    for obj in ELBOW_OBJECTS:
        assert len(od[obj.index]) == obj.bits, hex(obj.index)
        assert mappable_object(od, obj.mapping_entry) == obj
    assert od[objects.ENCODER_RESOLUTION][1].default == 2**19
    assert od[objects.TPDO_COMM][1].default == 0x182


def test_default_layout_round_trips_and_rejects_wrong_length():
    values = {objects.CONTROLWORD: 0x0F, objects.TARGET_CURRENT: -5600}
    data = pdo_layout.encode(pdo_layout.RPDO_COMMAND, values)
    assert len(data) == 6
    assert pdo_layout.decode(pdo_layout.RPDO_COMMAND, data) == values
    with pytest.raises(ValueError, match="5 bytes received, 6 expected"):
        pdo_layout.decode(pdo_layout.RPDO_COMMAND, data[:5])


def test_mapping_entries_are_validated():
    od = canopen.import_od(str(eds_path()), 2)
    entry = pdo_layout.POSITION_ACTUAL.mapping_entry
    assert entry == 0x60640020
    assert mappable_object(od, entry) == pdo_layout.POSITION_ACTUAL
    with pytest.raises(ValueError, match="0x6064:00 with 16 bits"):
        mappable_object(od, 0x60640010)
    with pytest.raises(ValueError, match="0x1017:00 with 16 bits is not mappable"):
        mappable_object(od, 0x10170010)  # the heartbeat time is not PDO-mappable


@pytest.mark.parametrize("spec,expected", [
    ("vcan0", {"interface": "socketcan", "channel": "vcan0"}),
    ("socketcan:can1", {"interface": "socketcan", "channel": "can1"}),
    ("virtual:x", {"interface": "virtual", "channel": "x", "receive_own_messages": False}),
    ("udp_multicast:239.0.0.1", {"interface": "udp_multicast", "channel": "239.0.0.1",
                                 "port": 43113, "receive_own_messages": False}),
    ("udp_multicast:239.1.2.3:5000", {"interface": "udp_multicast", "channel": "239.1.2.3",
                                      "port": 5000, "receive_own_messages": False}),
    # every other python-can interface, its channel in the interface's own syntax
    ("pcan:PCAN_USBBUS1", {"interface": "pcan", "channel": "PCAN_USBBUS1"}),
    ("kvaser:0", {"interface": "kvaser", "channel": "0"}),
    ("slcan:/dev/ttyACM0@115200", {"interface": "slcan", "channel": "/dev/ttyACM0@115200"}),
    ("ixxat:", {"interface": "ixxat"}),
])
def test_bus_specs(spec, expected):
    assert parse_bus_spec(spec) == expected


@pytest.mark.parametrize("spec,message", [
    ("", "empty bus spec"),
    ("can:0", "unknown interface 'can'; expected ethercat or one of python-can's: canalystii"),
    ("udp_multicast:10.0.0.1", "not a multicast group"),
    ("udp_multicast:239.0.0.1:99999", "port '99999'"),
    ("virtual:", "needs a channel name"),
    ("vcan 0", "not a SocketCAN interface name"),
])
def test_bad_bus_specs(spec, message):
    with pytest.raises(BusSpecError, match=message):
        parse_bus_spec(spec)
