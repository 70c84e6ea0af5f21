"""`dashboard`: watch and steer actuatord over Zenoh.

    dashboard foxglove [--prefix actuators/elbow] [--port 8765]   Foxglove WebSocket bridge
    dashboard tui [--prefix actuators/elbow]           terminal dashboard
    dashboard set reference '{"kind": "setpoint", "position": -1.0}'
    dashboard set weights position=300 torque_barrier=50
"""

import argparse
import json
import signal
import socket
import sys
import threading

from commands.log_options import (
    add_logging_argument,
    configure_logging,
    job_error,
    reports_failures,
)
from commands.model_options import parse_assignments
from commands.parsing import TCP_PORT, CommandParser, usage_error
from commands.zenoh_options import add_zenoh_arguments, check_key_expr, open_session
from protocol import telemetry

PROG = "dashboard"


def build_parser() -> CommandParser:
    parser = CommandParser(prog=PROG, description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[2:]))
    jobs = parser.add_subparsers(dest="job", required=True)
    fox = jobs.add_parser("foxglove", help="serve the telemetry to Foxglove")
    fox.add_argument("--prefix", default=telemetry.DEFAULT_PREFIX,
                     help="actuatord's key prefix: its services and liveliness "
                          "(default: %(default)s)")
    fox.add_argument("--key", help="key expression to bridge (default: PREFIX/**)")
    fox.add_argument("--host", default="127.0.0.1")
    fox.add_argument("--port", type=TCP_PORT, default=8765,
                     help="WebSocket port, 1..65535, serving both subprotocols, "
                          "foxglove.sdk.v1 (Foxglove) and foxglove.websocket.v1 (Lichtblick, "
                          "@foxglove/ws-protocol) (default: %(default)s)")
    fox.add_argument("--legacy-port", type=TCP_PORT, metavar="PORT",
                     help="serve the same on this port too (kept for setups that named a "
                          "second port for foxglove.websocket.v1; --port now serves it)")
    tui = jobs.add_parser("tui", help="terminal dashboard")
    tui.add_argument("--prefix", default=telemetry.DEFAULT_PREFIX)
    change = jobs.add_parser("set", help="change the reference or the weights")
    change.add_argument("what", choices=("reference", "weights"))
    change.add_argument("values", nargs="+",
                        help="reference: one JSON object; weights: NAME=VALUE ...")
    change.add_argument("--prefix", default=telemetry.DEFAULT_PREFIX)
    for sub in (fox, tui, change):
        add_zenoh_arguments(sub)
        add_logging_argument(sub)
    return parser


@reports_failures(PROG)
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(PROG, args.log_level)
    try:
        if args.job == "set":
            payload = _request_payload(args.what, args.values)
        check_key_expr("--prefix", args.prefix, wildcards=False)
        if args.job == "foxglove":
            if args.key is not None:
                check_key_expr("--key", args.key, wildcards=True)
            if args.legacy_port == args.port:
                raise ValueError(f"--legacy-port {args.legacy_port}: the same as --port; "
                                 "expected a port of its own")
            for port in (args.port, args.legacy_port):
                if port is not None:
                    _check_port_free(args.host, port)
        session = open_session(args)
    except ValueError as exc:
        return usage_error(PROG, str(exc))
    try:
        if args.job == "foxglove":
            return _foxglove(session, args)
        if args.job == "tui":
            from dashboard.tui import run_tui

            run_tui(session, args.prefix)
            return 0
        return _set(session, args, payload)
    finally:
        session.close()


def _check_port_free(host: str, port: int) -> None:
    """The bridge's port must be free: found out before the Zenoh session opens (the port
    could still be taken in between, which the bridge then reports)."""
    try:
        with socket.socket() as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers do
            probe.bind((host, port))
    except OSError as exc:
        raise ValueError(f"--host {host} --port {port}: cannot listen there: "
                         f"{exc.strerror or exc}") from None


def _request_payload(what: str, values: list[str]) -> str:
    if what == "reference":
        if len(values) != 1:
            raise ValueError("reference: give one JSON object")
        return values[0]
    weights = parse_assignments(values, None, "weights")
    return json.dumps(weights)


def _set(session, args: argparse.Namespace, payload: str) -> int:
    from dashboard.changes import NoAnswer, request_change

    try:
        answers = request_change(session, args.prefix, args.what, payload)
    except NoAnswer as exc:
        return job_error(PROG, str(exc))
    for answer in answers:
        if answer.accepted:
            print(f"dashboard: {args.what} accepted: {json.dumps(answer.change)}")
        else:
            print(f"dashboard: {args.what} refused: {answer.reason}", file=sys.stderr)
    return 0 if all(a.accepted for a in answers) else 1


def _foxglove(session, args: argparse.Namespace) -> int:
    from dashboard.foxglove_bridge import FoxgloveBridge

    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    key = args.key or f"{args.prefix}/**"
    extra = [] if args.legacy_port is None else [args.legacy_port]
    try:
        bridge = FoxgloveBridge(session, key, args.prefix, args.host, args.port, extra)
    except (OSError, RuntimeError) as exc:  # a port taken since it was checked
        return usage_error(PROG, f"--port {args.port}: {exc}")
    also = "".join(f" and ws://{args.host}:{port}" for port in bridge.ports[1:])
    print(f"dashboard: Foxglove bridge on ws://{args.host}:{bridge.port}{also} for {key} "
          "(subprotocols foxglove.sdk.v1 and foxglove.websocket.v1)", flush=True)
    stop.wait()
    bridge.close()
    print(f"dashboard: forwarded {bridge.forwarded} messages", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
