"""Bus specs as users type them (`vcan0`, `virtual:NAME`, `udp_multicast:GROUP[:PORT]`) turned
into python-can constructor arguments, and `ethercat:IFACE` (an Ethernet interface carrying an
EtherCAT line) into its interface name. Pure: opening the bus is the caller's job."""

import ipaddress
import re

_SOCKETCAN_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_.-]{0,14}$")
_NETWORK_INTERFACE_NAME = _SOCKETCAN_NAME  # Linux: IFNAMSIZ - 1 characters
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
        raise BusSpecError(f"bus spec {spec!r}: EtherCAT is not a CAN bus (ethercat_interface "
                           "reads it)")
    raise BusSpecError(f"bus spec {spec!r}: unknown interface {kind!r}; expected socketcan, "
                       "virtual, udp_multicast or ethercat")


def ethercat_interface(spec: str) -> str | None:
    """The Ethernet interface of an `ethercat:IFACE` spec; None for every other kind of spec
    (CAN buses, see `parse_bus_spec`)."""
    if not isinstance(spec, str):
        return None
    kind, sep, rest = spec.strip().partition(":")
    if kind != ETHERCAT or not sep:
        return None
    if not _NETWORK_INTERFACE_NAME.match(rest):
        raise BusSpecError(f"bus spec {spec!r}: {rest!r} is not a network interface name "
                           "(expected e.g. ethercat:eth1)")
    return rest


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
