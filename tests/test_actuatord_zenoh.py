"""`actuatord --sim --lockstep` in its own process, watched by a separate Zenoh session the way
a dashboard would, with nothing but the documented schema."""

import json
import subprocess
import sys
import time

import pytest
import zenoh

from protocol import telemetry
from tests.conftest import free_port, wait_for

pytestmark = pytest.mark.subprocess  # runs the commands as processes

PREFIX = "test/elbow"


def dashboard_session(port: int) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(config)


def start_actuatord(port: int, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep", "--prefix", PREFIX,
         "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_dashboard_session_decodes_state_and_talks_to_the_queryables():
    port = free_port()
    proc = start_actuatord(port, "--duration", "600")  # stopped by the test (SIGTERM)
    received: dict[str, list] = {topic: [] for topic in telemetry.topics(1)}
    session = dashboard_session(port)
    try:
        subscribers = [session.declare_subscriber(
            telemetry.key_expr(PREFIX, topic),
            lambda sample, topic=topic: received[topic].append(sample.payload.to_bytes()))
            for topic in telemetry.topics(1)]
        # the first test of a fresh clone waits for numba to compile the solver and the
        # physics (34 s on a quiet host, over 60 s at load 7)
        wait_for(lambda: len(received["state"]) >= 200, 240, 0.05)
        assert len(received["state"]) >= 200, proc.stderr.read() if proc.poll() else "no state"

        replies = list(session.get(telemetry.key_expr(PREFIX, telemetry.PARAMETERS)))
        parameters = json.loads(replies[0].ok.payload.to_bytes())
        assert parameters["limits"]["current_max"] == 6.0
        assert parameters["settings"]["horizon"] == 100

        refused = list(session.get(telemetry.key_expr(PREFIX, telemetry.REFERENCE),
                                   payload=json.dumps({"kind": "setpoint", "position": -9})))
        answer = json.loads(refused[0].ok.payload.to_bytes())
        assert answer["ok"] is False and "spans" in answer["reason"]
        accepted = list(session.get(telemetry.key_expr(PREFIX, telemetry.REFERENCE),
                                    payload=json.dumps({"kind": "setpoint", "position": -1.0})))
        assert json.loads(accepted[0].ok.payload.to_bytes())["ok"] is True
        time.sleep(1.0)
        for subscriber in subscribers:
            subscriber.undeclare()
    finally:
        session.close()
        proc.terminate()
        out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "cycles" in out and "drive" not in err

    states = [telemetry.decode("State", data) for data in received["state"]]
    assert all(s.drive_state == "operation enabled" for s in states)
    assert all(-2.5 < s.position < 0.2 for s in states)
    times = [s.t for s in states]
    assert times == sorted(times)
    commands = [telemetry.decode("Command", data) for data in received["command"]]
    assert all(abs(c.current) <= c.current_limit == 6.0 for c in commands)
    assert commands[-1].reference_position == -1.0  # the accepted reference took effect
    faults = [telemetry.decode("Fault", data) for data in received["fault"]]
    assert any("reference refused" in f.cause for f in faults), [f.cause for f in faults]
    plan = telemetry.decode("Plan", received["plan"][-1])
    assert len(plan.position) == 101 and len(plan.current) == 100
    solver = telemetry.decode("SolverStats", received["solver"][-1])
    assert solver.status in ("converged", "max_iterations")


def test_sigterm_disables_and_exits_zero_with_loop_statistics():
    port = free_port()
    proc = start_actuatord(port)
    line = proc.stdout.readline()
    assert "enabled" in line, proc.stderr.read()
    time.sleep(1.0)
    proc.terminate()
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "stop requested" in out and "MPC tick median" in out


def test_bad_input_exits_2_with_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "commands.actuatord", "--sim", "--reference",
                           '{"kind": "setpoint", "position": "up"}'],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip() == ("actuatord: error: setpoint.position: expected a finite "
                                   "number, got 'up'")


def test_shipped_proto_file_matches_the_schema():
    from importlib.resources import files

    assert (files("protocol") / "telemetry.proto").read_text() == telemetry.proto_text()


def test_recorder_writes_live_telemetry_to_mcap(tmp_path):
    from pathlib import Path

    from recorder.mcap_io import iter_mcap
    from recorder.reader import load_recording

    port = free_port()
    proc = start_actuatord(port, "--duration", "60")
    output = tmp_path / "live.mcap"
    try:
        assert "enabled" in proc.stdout.readline()
        started = time.time_ns()
        rec = subprocess.run(
            [sys.executable, "-m", "commands.recorder", "--zenoh", f"{PREFIX}/**", "-o",
             str(output), "--duration", "2", "--connect", f"tcp/127.0.0.1:{port}",
             "--no-multicast-scouting"], capture_output=True, text=True, timeout=60)
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
    assert rec.returncode == 0, rec.stderr
    topics = {topic for topic, *_ in iter_mcap(Path(output)) if topic != "metadata"}
    assert {f"{PREFIX}/state", f"{PREFIX}/command", f"{PREFIX}/solver"} <= topics
    recording = load_recording(output)
    assert len(recording) > 100
    assert all(telemetry.decode("Command", data).current_limit == 6.0
               for topic, _, _, data, _ in iter_mcap(Path(output)) if topic.endswith("/command"))
    # log_time: the wall clock when each sample arrived
    assert all(started <= log_time <= time.time_ns() for _, _, log_time, *_ in iter_mcap(output))
    # publish_time: the drive time the sample speaks for, on one time base for the prefix
    from mcap.reader import make_reader

    with open(output, "rb") as fh:
        stamps = [(message.publish_time, telemetry.decode("State", message.data).t)
                  for _, channel, message in make_reader(fh).iter_messages(log_time_order=False)
                  if channel.topic == f"{PREFIX}/state"]
    epochs = {publish - round(t * 1e9) for publish, t in stamps}
    assert len(epochs) == 1 and abs(epochs.pop() - started) < 60e9
