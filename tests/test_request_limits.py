"""Zenoh requests cannot stall or crash the loop: oversized bodies are refused unread, hostile
JSON is refused before the parser follows it, internal errors become one refused request, and
every request leaves an audit line of at most 1 KiB."""

import contextlib
import json
import logging
import subprocess
import sys
import threading
import time

import pytest
import zenoh

from controller import requests
from controller.loop import ControlLoop, LoopOptions
from controller.mpc import Mpc
from controller.requests import AUDIT_LINE_MAX, MAX_BODY, Body, RequestHandler
from controller.telemetry import TelemetryPublisher
from driver.canopen_drive import CanOpenDrive
from driver.clock import DriveClock
from driver.drive_group import single_joint
from model.parameters import Payload, load_model
from protocol import telemetry
from sim_bus.embedded import EmbeddedDrive
from sim_bus.plant import SensorNoise
from tests.conftest import free_port, virtual_pair, wait_for

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
        loop = ControlLoop(single_joint(drive), mpc, LoopOptions(clock=DriveClock()))
        yield RequestHandler(loop, 0, MODEL, Payload(), audit.append), audit


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
    assert handler.joint.settings.weights.position == 400.0  # not before the next cycle


class BlockedTime:
    """How long the loop's thread has been blocked (neither running nor waiting for a core):
    wall time minus its CPU time and its run-queue time, read by the loop's own thread at the
    start of a cycle (a thread's own counters are exact; another thread's lag by a scheduler
    tick). In lock-step on the embedded drive the loop blocks only to wait for the interpreter
    lock, so this is the time other threads' Python took from it, and a busy machine (run-queue
    time) does not count."""

    def __init__(self, loop: ControlLoop):
        self.loop = loop

    def __call__(self) -> float:
        taken = threading.Event()
        reading = []

        def read() -> None:
            with open(f"/proc/self/task/{threading.get_native_id()}/schedstat") as f:
                waiting = int(f.read().split()[1])
            reading.append(time.perf_counter() - time.thread_time() - waiting * 1e-9)
            taken.set()

        self.loop.request(read)
        assert taken.wait(10), f"the loop stopped: {self.loop.report.reason}"
        return reading[0]


# A Zenoh client in its own process, as a dashboard or an attacker would be: building and
# sending a 64 MB payload costs that process, not the loop's. One request per line on stdin
# ("KEY SIZE": a body of SIZE bytes that is costly JSON), one JSON line per reply on stdout.
CLIENT = """
import json, sys, zenoh
config = zenoh.Config()
config.insert_json5("connect/endpoints", json.dumps([sys.argv[1]]))
config.insert_json5("scouting/multicast/enabled", "false")
session = zenoh.open(config)
print("ready", flush=True)
for line in sys.stdin:
    key, size = line.split()
    head = b'{"kind": "setpoint", "position": -1.0, "pad": ['
    payload = head + b"0," * ((int(size) - len(head)) // 2) + b"0]}"
    replies = list(session.get(key, payload=payload, timeout=30))
    answer = json.loads(replies[0].ok.payload.to_bytes()) if replies else None
    print(json.dumps({"bytes": len(payload), "answer": answer}), flush=True)
"""


@pytest.fixture(scope="module")
def service():
    """actuatord's pieces in this process: a lock-step loop on a virtual drive, its Zenoh
    publisher and queryables; a client in another process; the audit lines as they arrive."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    config = zenoh.Config()
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    # each part closed however the set-up ends (an unclosed Zenoh session's callback thread
    # would keep the test process alive after the suite)
    with contextlib.ExitStack() as cleanup:
        server = zenoh.open(config)
        cleanup.callback(server.close)
        publisher = TelemetryPublisher(server, PREFIX)
        cleanup.callback(publisher.close)
        audit: list[bytes] = []
        server.declare_subscriber(telemetry.key_expr(PREFIX, telemetry.AUDIT),
                                  lambda sample: audit.append(sample.payload.to_bytes()))
        mpc = Mpc(MODEL)
        client = subprocess.Popen([sys.executable, "-c", CLIENT, endpoint],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        cleanup.callback(client.wait, 30)
        cleanup.callback(client.stdin.close)
        # lock-step on both sides: every watchdog counts cycles, so a busy machine does not
        # end the loop while this test measures what requests cost it
        sim = EmbeddedDrive(MODEL, Payload(), SensorNoise(), clock=DriveClock())
        cleanup.callback(sim.close)
        drive = CanOpenDrive(sim.master_network, 2, velocity_limit=MODEL.limits.velocity_max,
                             clock=DriveClock(), response_timeout=1.0)
        cleanup.callback(drive.close)
        drive.start()
        loop = ControlLoop(single_joint(drive), mpc, LoopOptions(clock=DriveClock()),
                           [publisher.publish])
        handler = RequestHandler(loop, 0, MODEL, Payload(), publisher.publish_audit)
        publisher.serve_json(telemetry.PARAMETERS, handler.parameters)
        publisher.serve_json(telemetry.REFERENCE, handler.set_reference)
        runner = threading.Thread(target=loop.run, daemon=True)
        runner.start()
        cleanup.callback(runner.join, 10)
        cleanup.callback(loop.stop)
        assert client.stdout.readline().strip() == "ready"
        time.sleep(1.0)

        def request(key: str, size: int) -> dict:
            client.stdin.write(f"{telemetry.key_expr(PREFIX, key)} {size}\n")
            client.stdin.flush()
            return json.loads(client.stdout.readline())

        yield request, BlockedTime(loop), audit, loop


def extra_missed_cycles(blocked: BlockedTime, loop: ControlLoop, query) -> tuple[int, list]:
    """The periods the loop's thread was kept from running while `query()` ran (from sending
    the request to its reply), beyond its blocked time at the same rate just before: the
    cycles the request cost a real-time loop. Best of three: what the request costs shows every
    time; a thread preempted by the machine's other work while holding the interpreter lock
    (the loop then blocks on the lock) does not."""
    extras, replies = [], []
    for _ in range(3):
        assert loop.report.reason == "stopped", loop.report.reason  # still running
        before, start = blocked(), time.perf_counter()
        time.sleep(0.3)
        rate = max(blocked() - before, 0.0) / (time.perf_counter() - start)
        start, cycles = time.perf_counter(), loop.report.cycles
        during = blocked()
        replies.append(query())
        during = blocked() - during
        duration = time.perf_counter() - start
        assert loop.report.cycles > cycles  # the loop ran meanwhile
        extras.append(int(max(during - rate * duration, 0.0) / PERIOD))
    return min(extras), replies


@pytest.mark.real_time
def test_a_4_mb_reference_request_is_refused_without_stalling_the_loop(service):
    request, blocked, audit, loop = service
    before = len(audit)
    # costly to parse: two million numbers (the old path spent seconds of interpreter time)
    extra, replies = extra_missed_cycles(blocked, loop, lambda: request(telemetry.REFERENCE,
                                                                        4 * 1024 * 1024))
    assert all(r["answer"]["ok"] is False and "refused unread" in r["answer"]["reason"]
               for r in replies)
    assert extra <= 2
    wait_for(lambda: len(audit) >= before + 3, 5.0, 0.05)
    lines = audit[before:]
    assert len(lines) == 3 and all(len(line) <= AUDIT_LINE_MAX for line in lines)
    assert json.loads(lines[0])["payload_bytes"] == replies[0]["bytes"] > 4_000_000
    assert loop.report.exit_code == 0 and loop.report.cycles > 100


@pytest.mark.real_time
def test_a_64_mb_parameters_query_does_not_stall_the_loop(service):
    request, blocked, _, loop = service
    extra, replies = extra_missed_cycles(blocked, loop, lambda: request(telemetry.PARAMETERS,
                                                                        64 * 1024 * 1024))
    assert all(r["answer"]["ok"] is False and "refused unread" in r["answer"]["reason"]
               for r in replies)
    assert extra <= 2
    assert MAX_BODY == 64 * 1024
