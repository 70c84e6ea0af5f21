"""Bus specs as users type them (`vcan0`, `virtual:NAME`, `udp_multicast:GROUP[:PORT]`,
`ethercat:IFACE`, `INTERFACE:CHANNEL` for any other python-can interface) turned into
constructor arguments: python-can's for CAN, the network interface for EtherCAT. Pure: opening
the bus is the caller's job."""

import ipaddress
import re

from can import VALID_INTERFACES

_SOCKETCAN_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_.-]{0,14}$")
_NETWORK_INTERFACE = _SOCKETCAN_NAME  # Linux IFNAMSIZ: 15 characters
ETHERCAT = "ethercat"
DEFAULT_UDP_PORT = 43113  # python-can's UdpMulticastBus default


class BusSpecError(ValueError):
    """A bus spec that names no usable interface."""


def parse_bus_spec(spec: str) -> dict:
    """Return python-can kwargs (`interface`, `channel`, ...) for a bus spec."""
    if not isinstance(spec, str) or not spec.strip():
        raise BusSpecError("empty bus spec; expected e.g. vcan0, virtual:NAME or "
                           "udp_multicast:239.0.0.1")
    spec = spec.strip()
    kind, sep, rest = spec.partition(":")
    if not sep:
        if _SOCKETCAN_NAME.match(spec):
            return {"interface": "socketcan", "channel": spec}
        raise BusSpecError(f"bus spec {spec!r}: not a SocketCAN interface name")
    if kind == "socketcan":
        if _SOCKETCAN_NAME.match(rest):
            return {"interface": "socketcan", "channel": rest}
        raise BusSpecError(f"bus spec {spec!r}: not a SocketCAN interface name")
    if kind == "virtual":
        if not rest:
            raise BusSpecError(f"bus spec {spec!r}: virtual needs a channel name")
        return {"interface": "virtual", "channel": rest, "receive_own_messages": False}
    if kind == "udp_multicast":
        return _udp_multicast(spec, rest)
    if kind == ETHERCAT:
        if _NETWORK_INTERFACE.match(rest):
            return {"interface": ETHERCAT, "channel": rest}
        raise BusSpecError(f"bus spec {spec!r}: not a network interface name")
    if kind in VALID_INTERFACES:
        # the interface's own channel syntax (PCAN_USBBUS1, /dev/ttyACM0@115200, 0, ...);
        # none given: the interface's default channel
        return {"interface": kind, "channel": rest} if rest else {"interface": kind}
    raise BusSpecError(f"bus spec {spec!r}: unknown interface {kind!r}; expected ethercat or "
                       f"one of python-can's: {', '.join(sorted(VALID_INTERFACES))}")


def is_ethercat(spec: str) -> bool:
    """Whether a spec names an EtherCAT segment rather than a CAN bus."""
    return isinstance(spec, str) and spec.strip().partition(":")[0] == ETHERCAT


def _udp_multicast(spec: str, rest: str) -> dict:
    port = DEFAULT_UDP_PORT
    group = rest
    if rest.startswith("["):
        group, _, tail = rest[1:].partition("]")
        if tail:
            port = _port(spec, tail.lstrip(":"))
    elif rest.count(":") == 1:
        group, port_text = rest.split(":")
        port = _port(spec, port_text)
    try:
        address = ipaddress.ip_address(group)
    except ValueError:
        raise BusSpecError(f"bus spec {spec!r}: {group!r} is not an IP address") from None
    if not address.is_multicast:
        raise BusSpecError(f"bus spec {spec!r}: {group} is not a multicast group")
    return {"interface": "udp_multicast", "channel": str(address), "port": port,
            "receive_own_messages": False}


def _port(spec: str, text: str) -> int:
    if not text.isdigit() or not 0 < int(text) < 65536:
        raise BusSpecError(f"bus spec {spec!r}: port {text!r} is not in 1..65535")
    return int(text)
