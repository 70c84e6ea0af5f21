"""The Zenoh session options, spelled like Zenoh's own tools (`--listen`, `--connect`,
`--zenoh-config`, `--no-multicast-scouting`), and key expressions checked before use."""

from __future__ import annotations

import argparse
import ipaddress
import json

import zenoh

from commands.file_options import check_input_option


def check_key_expr(option: str, text: str, wildcards: bool) -> str:
    """A Zenoh key expression (`wildcards` allows `*`, `**`, `$*`: subscriptions do, a
    publishing prefix does not). ValueError names the option and the rule broken."""
    if not wildcards and any(c in text for c in "*$"):
        raise ValueError(f"{option} {text!r}: expected a key prefix without wildcards "
                         "(*, **, $*), e.g. actuators/elbow")
    try:
        zenoh.KeyExpr(text)
    except Exception as exc:  # zenoh raises its own ZError; keep its reason, not its source
        reason = str(exc).split(" at /", 1)[0]
        raise ValueError(f"{option} {text!r}: not a Zenoh key expression: {reason}") from None
    return text


# Zenoh's locators over IP: PROTOCOL/HOST:PORT (an IPv6 host in brackets)
_IP_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_OTHER_PROTOCOLS = ("unixsock-stream", "unixpipe", "serial", "vsock")


def check_endpoint(option: str, text: str) -> str:
    """A Zenoh endpoint `PROTOCOL/ADDRESS[?config][#metadata]`, with HOST:PORT over IP
    (`tcp/127.0.0.1:7447`, `tcp/[::1]:7447`): Zenoh itself ignores a malformed one without a
    word, so a session would silently miss its peer. ValueError names the option."""
    locator = text.split("#", 1)[0].split("?", 1)[0]
    protocol, sep, address = locator.partition("/")
    expected = "expected PROTOCOL/HOST:PORT, e.g. tcp/127.0.0.1:7447 or tcp/[::1]:7447"
    if not sep or not address or protocol not in _IP_PROTOCOLS + _OTHER_PROTOCOLS:
        raise ValueError(f"{option} {text[:80]!r}: {expected}")
    if protocol in _IP_PROTOCOLS:
        host, colon, port = address.rpartition(":")
        if host.startswith("["):
            inner = host[1:-1] if host.endswith("]") else ""
            try:
                ok = bool(inner) and ipaddress.IPv6Address(inner.split("%", 1)[0]) is not None
            except ValueError:
                ok = False
        else:
            ok = bool(host) and all(c.isalnum() or c in "-._" for c in host)
        if not (colon and ok and port.isdigit() and int(port) <= 65535):
            raise ValueError(f"{option} {text[:80]!r}: {expected}")
    return text


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("Zenoh")
    group.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable)")
    group.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                       help="endpoint to connect to (repeatable)")
    group.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config file")
    group.add_argument("--no-multicast-scouting", action="store_true",
                       help="disable multicast scouting (peers only via --connect/--listen)")


def zenoh_config(args: argparse.Namespace) -> zenoh.Config:
    """A Zenoh config from the file (if any) with the command-line options applied on top.
    Raises ValueError naming the option at fault."""
    if args.zenoh_config is not None:
        check_input_option("--zenoh-config", args.zenoh_config, "a Zenoh JSON5 config")
    try:
        config = zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config else (
            zenoh.Config())
    except Exception as exc:  # zenoh raises its own ZError for unreadable or invalid files
        raise ValueError(f"--zenoh-config {args.zenoh_config}: {exc}") from None
    for option, key in (("listen", "listen/endpoints"), ("connect", "connect/endpoints")):
        endpoints = getattr(args, option)
        for endpoint in endpoints:
            check_endpoint(f"--{option}", endpoint)
        if endpoints:
            try:
                config.insert_json5(key, json.dumps(endpoints))
            except Exception as exc:
                raise ValueError(f"--{option} {' '.join(endpoints)}: {exc}") from None
    if args.no_multicast_scouting:
        config.insert_json5("scouting/multicast/enabled", "false")
    return config


def open_session(args: argparse.Namespace) -> zenoh.Session:
    config = zenoh_config(args)
    try:
        return zenoh.open(config)
    except Exception as exc:
        raise ValueError(f"cannot open the Zenoh session: {exc}") from None
