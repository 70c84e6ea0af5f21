"""Zenoh requests cannot stall or crash the loop: oversized bodies are refused unread, hostile
JSON is refused before the parser follows it, internal errors become one refused request, and
every request leaves an audit line of at most 1 KiB."""

import json
import logging
import threading
import time

import pytest
import zenoh

from controller import requests
from controller.loop import ControlLoop, LoopOptions
from controller.messages import State
from controller.mpc import Mpc
from controller.requests import AUDIT_LINE_MAX, MAX_BODY, Body, RequestHandler
from controller.telemetry import TelemetryPublisher
from model.parameters import Payload, load_model
from protocol import telemetry
from tests.conftest import free_port, virtual_pair

MODEL = load_model()
PREFIX = "test/limits"
PERIOD = 1e-3


def body(data: bytes) -> Body:
    return Body(len(data), lambda: data)


def unreadable(size: int) -> Body:
    def read() -> bytes:
        raise AssertionError("an oversized body was read")
    return Body(size, read)


@pytest.fixture(scope="module")
def handler():
    """A request handler on a loop that is built but not run (requests queue up)."""
    mpc = Mpc(MODEL)
    with virtual_pair() as (_, drive):
        audit: list[str] = []
        loop = ControlLoop(drive, mpc, LoopOptions(lockstep=True))
        yield RequestHandler(loop, mpc, MODEL, Payload(), audit.append), audit


def refused(handler, answer, audit, needle: str) -> dict:
    assert answer["ok"] is False and needle in answer["reason"], answer
    line = audit[-1]
    assert len(line.encode()) <= AUDIT_LINE_MAX
    record = json.loads(line)
    assert record["accepted"] is False and needle in record["reason"]
    return record


@pytest.mark.parametrize("what", ["reference", "weights"])
def test_a_body_over_the_limit_is_refused_unread(handler, what):
    handler, audit = handler
    answer = getattr(handler, f"set_{what}")(unreadable(4 * 1024 * 1024))
    record = refused(handler, answer, audit, "refused unread")
    assert record["payload_bytes"] == 4 * 1024 * 1024 and record["request"] == what


def test_a_parameters_query_with_a_huge_body_is_refused_unread(handler):
    handler, audit = handler
    refused(handler, handler.parameters(unreadable(64 * 1024 * 1024)), audit, "refused unread")
    assert handler.parameters(body(b"ignored"))["limits"]["current_max"] == 6.0


@pytest.mark.parametrize("data,needle", [
    (b'{"position": ' + b"1" * 401 + b"}", "a number of 401 characters"),
    (b"[" * 50_000 + b"]" * 50_000, "refused unread"),  # 100 kB: over the size limit
    (b"[" * 20_000 + b"]" * 20_000, "'{' or '['"),  # 40 kB: too deep to parse
    (b'{"position": [' + b"0," * 10_000 + b"0]}", "','"),
    (b'{"position": 300', "not JSON"),
    (b'{"position": "\xff"}', "not UTF-8"),
])
def test_hostile_json_is_refused_with_a_reason_and_audited(handler, data, needle):
    handler, audit = handler
    refused(handler, handler.set_weights(body(data)), audit, needle)


def test_an_audit_line_quotes_a_bounded_excerpt_whatever_the_payload(handler):
    handler, audit = handler
    data = b'{"kind": "' + b"\\u0001" * 10_000 + b'"}'  # quoted back, each one grows to 7
    record = refused(handler, handler.set_reference(body(data)), audit, "reference kind")
    assert record["payload"] and data.decode().startswith(record["payload"])
    assert record["payload_bytes"] == len(data)
    assert len(json.loads(json.dumps(record))["reason"]) <= requests.REASON_MAX


def test_an_internal_error_is_one_refused_and_audited_request(handler, monkeypatch, caplog):
    handler, audit = handler

    def broken(spec, limits):
        raise RuntimeError("a bug")

    monkeypatch.setattr(requests, "reference_from_dict", broken)
    with caplog.at_level(logging.ERROR, logger="controller.requests"):
        answer = handler.set_reference(body(b'{"kind": "setpoint", "position": -1}'))
    refused(handler, answer, audit, "internal error (RuntimeError)")
    assert all(record.exc_info is None for record in caplog.records)  # no traceback


def test_an_accepted_request_is_applied_by_the_loop_and_audited(handler):
    handler, audit = handler
    answer = handler.set_weights(body(b'{"position": 300}'))
    assert answer == {"ok": True, "weights": {"position": 300}}
    assert json.loads(audit[-1])["accepted"] is True
    assert handler.mpc.settings.weights.position == 400.0  # not before the next cycle


class CycleTimes:
    """Wall time of every cycle of a lock-step loop (a subscriber of its State messages)."""

    def __init__(self):
        self.times: list[float] = []

    def __call__(self, message) -> None:
        if type(message) is State:
            self.times.append(time.perf_counter())

    def missed(self, start: float, end: float) -> int:
        """Cycles a real-time loop would have missed in [start, end]: each gap between cycles
        longer than a period counts as many periods as it lasted (as the loop's clock does)."""
        times = [t for t in self.times if start <= t <= end]
        return sum(int((b - a) / PERIOD) for a, b in zip(times, times[1:], strict=False)
                   if b - a > PERIOD)


@pytest.fixture(scope="module")
def service():
    """actuatord's pieces in this process: a lock-step loop on a virtual drive, its Zenoh
    publisher and queryables, and a client session."""
    port = free_port()
    config = zenoh.Config()
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    server = zenoh.open(config)
    publisher = TelemetryPublisher(server, PREFIX)
    cycles = CycleTimes()
    mpc = Mpc(MODEL)
    with virtual_pair(response_timeout=1.0) as (_, drive):
        drive.start()
        loop = ControlLoop(drive, mpc, LoopOptions(lockstep=True),
                           [publisher.publish, cycles])
        handler = RequestHandler(loop, mpc, MODEL, Payload(), publisher.publish_audit)
        publisher.serve_json(telemetry.PARAMETERS, handler.parameters)
        publisher.serve_json(telemetry.REFERENCE, handler.set_reference)
        runner = threading.Thread(target=loop.run, daemon=True)
        runner.start()
        client_config = zenoh.Config()
        client_config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        client_config.insert_json5("scouting/multicast/enabled", "false")
        client = zenoh.open(client_config)
        audit: list[bytes] = []
        client.declare_subscriber(telemetry.key_expr(PREFIX, telemetry.AUDIT),
                                  lambda sample: audit.append(sample.payload.to_bytes()))
        time.sleep(1.0)
        try:
            yield client, cycles, audit, loop
        finally:
            loop.stop()
            runner.join(10)
            client.close()
            publisher.close()
            server.close()


def extra_missed_cycles(cycles: CycleTimes, query) -> tuple[int, list]:
    """Missed cycles while `query()` runs (until its reply is in) beyond those of an equally
    long window just before. Best of three: a stall the request causes shows every time, one
    the machine's other work causes does not."""
    extras, replies = [], []
    for _ in range(3):
        start = time.perf_counter()
        replies.append(query())
        end = time.perf_counter() + 0.05
        time.sleep(0.1)
        assert len([t for t in cycles.times if start <= t <= end]) > 10  # the loop ran
        extras.append(cycles.missed(start, end)
                      - cycles.missed(start - (end - start), start))
    return min(extras), replies


def test_a_4_mb_reference_request_is_refused_without_stalling_the_loop(service):
    client, cycles, audit, loop = service
    # costly to parse: a million numbers (the old path spent a second of interpreter time here)
    payload = b'{"kind": "setpoint", "position": -1.0, "pad": [' + b"0," * 2_000_000 + b"0]}"
    assert len(payload) > 4_000_000
    before = len(audit)
    extra, replies = extra_missed_cycles(cycles, lambda: list(client.get(
        telemetry.key_expr(PREFIX, telemetry.REFERENCE), payload=payload, timeout=20)))
    answers = [json.loads(reply[0].ok.payload.to_bytes()) for reply in replies]
    assert all(a["ok"] is False and "refused unread" in a["reason"] for a in answers)
    assert extra <= 2
    deadline = time.monotonic() + 5
    while len(audit) < before + 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    lines = audit[before:]
    assert len(lines) == 3 and all(len(line) <= AUDIT_LINE_MAX for line in lines)
    assert json.loads(lines[0])["payload_bytes"] == len(payload)
    assert loop.report.exit_code == 0 and loop.report.cycles > 1000


def test_a_64_mb_parameters_query_does_not_stall_the_loop(service):
    client, cycles, _, _ = service
    payload = bytes(64 * 1024 * 1024)
    extra, replies = extra_missed_cycles(cycles, lambda: list(client.get(
        telemetry.key_expr(PREFIX, telemetry.PARAMETERS), payload=payload, timeout=30)))
    assert all(json.loads(r[0].ok.payload.to_bytes())["ok"] is False for r in replies)
    assert extra <= 2
    assert MAX_BODY == 64 * 1024
