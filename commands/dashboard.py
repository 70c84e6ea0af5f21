"""`dashboard`: watch and steer actuatord over Zenoh.

    dashboard foxglove [--key KEYEXPR] [--port 8765]   Foxglove WebSocket bridge
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

from commands.options import (
    TCP_PORT,
    CommandParser,
    add_logging_argument,
    add_zenoh_arguments,
    check_key_expr,
    configure_logging,
    job_error,
    open_session,
    parse_assignments,
    usage_error,
)
from protocol import telemetry

PROG = "dashboard"


def build_parser() -> CommandParser:
    parser = CommandParser(prog=PROG, description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[2:]))
    jobs = parser.add_subparsers(dest="job", required=True)
    fox = jobs.add_parser("foxglove", help="serve the telemetry to Foxglove")
    fox.add_argument("--key", default=f"{telemetry.DEFAULT_PREFIX}/**",
                     help="key expression to bridge (default: %(default)s)")
    fox.add_argument("--host", default="127.0.0.1")
    fox.add_argument("--port", type=TCP_PORT, default=8765,
                     help="WebSocket port, 1..65535 (default: %(default)s)")
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


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(PROG, args.log_level)
    try:
        if args.job == "set":
            payload = _request_payload(args.what, args.values)
        if args.job == "foxglove":
            check_key_expr("--key", args.key, wildcards=True)
            _check_port_free(args.host, args.port)
        else:
            check_key_expr("--prefix", args.prefix, wildcards=False)
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
    key = telemetry.key_expr(args.prefix, args.what)
    replies = list(session.get(key, payload=payload, timeout=5.0))
    answers = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
    if not answers:
        return job_error(PROG, f"no actuatord answered on {key}")
    for answer in answers:
        if answer.get("ok"):
            print(f"dashboard: {args.what} accepted: {json.dumps(answer[args.what])}")
        else:
            print(f"dashboard: {args.what} refused: {answer.get('reason')}", file=sys.stderr)
    return 0 if all(a.get("ok") for a in answers) else 1


def _foxglove(session, args: argparse.Namespace) -> int:
    from dashboard.foxglove_bridge import FoxgloveBridge

    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        bridge = FoxgloveBridge(session, args.key, args.host, args.port)
    except RuntimeError as exc:  # foxglove-sdk's FoxgloveError: the port was taken meanwhile
        return usage_error(PROG, f"--port {args.port}: {exc}")
    print(f"dashboard: Foxglove bridge on ws://{args.host}:{args.port} for {args.key}",
          flush=True)
    stop.wait()
    bridge.close()
    print(f"dashboard: forwarded {bridge.forwarded} messages", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
