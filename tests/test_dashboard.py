"""Dashboards: the Foxglove bridge seen by a plain WebSocket client, the terminal dashboard
rendering live values, and the command path refusing bad changes with a reason."""

import asyncio
import json
import struct
import subprocess
import sys
import time
from importlib.resources import files

import pytest
import websockets

from protocol import telemetry
from tests.conftest import free_port
from tests.test_actuatord_zenoh import PREFIX, dashboard_session, start_actuatord

FOXGLOVE_SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


async def foxglove_client(port: int, wanted: str, count: int) -> tuple[list, list[bytes]]:
    """Connect like Foxglove does, subscribe to `wanted`, collect `count` message payloads."""
    deadline = time.monotonic() + 60
    while True:
        try:
            ws = await websockets.connect(f"ws://127.0.0.1:{port}", close_timeout=1,
                                          subprotocols=FOXGLOVE_SUBPROTOCOLS)
            break
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)
    channels, payloads = {}, []
    async with ws:
        while len(payloads) < count:
            frame = await asyncio.wait_for(ws.recv(), 30)
            if isinstance(frame, str):
                message = json.loads(frame)
                if message.get("op") == "advertise":
                    for channel in message["channels"]:
                        channels[channel["id"]] = channel
                        if channel["topic"] == wanted:
                            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                                {"id": 7, "channelId": channel["id"]}]}))
            elif frame[0] == 0x01:  # message data: opcode, subscription id, log time, payload
                subscription, _ = struct.unpack_from("<IQ", frame, 1)
                assert subscription == 7
                payloads.append(frame[13:])
    return list(channels.values()), payloads


def test_foxglove_bridge_advertises_and_forwards_decodable_messages():
    zenoh_port, ws_port = free_port(), free_port()
    actuatord = start_actuatord(zenoh_port, "--duration", "60")
    assert "enabled" in actuatord.stdout.readline()  # listening before the bridge connects
    bridge = subprocess.Popen(
        [sys.executable, "-m", "commands.dashboard", "foxglove", "--key", f"{PREFIX}/**", "--port",
         str(ws_port), "--connect", f"tcp/127.0.0.1:{zenoh_port}", "--no-multicast-scouting"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert "Foxglove bridge" in bridge.stdout.readline()
        channels, payloads = asyncio.run(foxglove_client(ws_port, f"/{PREFIX}/state", 50))
    finally:
        bridge.terminate()
        actuatord.terminate()
        bridge.communicate(timeout=30)
        actuatord.communicate(timeout=30)
    by_topic = {c["topic"]: c for c in channels}
    state = by_topic[f"/{PREFIX}/state"]
    assert state["encoding"] == "protobuf" and state["schemaName"] == "actuator.State"
    assert f"/{PREFIX}/command" in by_topic
    decoded = [telemetry.decode("State", p) for p in payloads]
    assert all(s.drive_state == "operation enabled" for s in decoded)
    assert decoded[-1].t > decoded[0].t


def test_layout_refers_to_topics_and_fields_that_exist():
    layout = json.loads((files("dashboard") / "elbow_layout.json").read_text())
    paths = [p["value"] for panel in layout["configById"].values() for p in panel.get("paths", [])]
    assert len(paths) >= 8
    for path in paths:
        topic, field = path.rsplit(".", 1)
        name = telemetry.TOPICS[topic.rsplit("/", 1)[-1]]
        assert field in [f[0] for f in telemetry.SCHEMAS[name]], path


def test_terminal_dashboard_renders_live_values_limits_and_faults():
    from dashboard.tui import ElbowDashboard

    async def scenario() -> str:
        app = ElbowDashboard(PREFIX)
        async with app.run_test(size=(100, 40)) as pilot:
            for k in range(50):
                app.ingest("state", telemetry.message_class("State")(
                    t=k * 0.02, position=-2.30, velocity=0.1, motor_current=-5.8,
                    joint_torque=-9.5, statusword=0x0237, drive_state="operation enabled"))
            app.ingest("command", telemetry.message_class("Command")(
                t=1.0, current=-5.8, planned_current=-5.8, reference_position=-2.5,
                current_limit=6.0, position_min=-2.35, position_max=0.0))
            app.ingest("solver", telemetry.message_class("SolverStats")(
                t=1.0, solve_time_us=17.5, iterations=1, status="max_iterations"))
            app.ingest("fault", telemetry.message_class("Fault")(
                t=1.0, source="controller", cause="solver not_finite: holding position",
                action="commanded -5.000 A (safe command)"))
            await pilot.pause()
            return app.export_screenshot()

    svg = asyncio.run(scenario())
    text = svg.replace("&#160;", " ")
    for needle in ("-2.3000", "reference", "-5.800", "17.5", "solver", "not_finite"):
        assert needle in text, needle


def test_refused_change_leaves_the_controller_unchanged_and_says_why():
    port = free_port()
    actuatord = start_actuatord(port, "--duration", "60")
    session = dashboard_session(port)
    audit: list[dict] = []
    try:
        assert "enabled" in actuatord.stdout.readline()
        session.declare_subscriber(telemetry.key_expr(PREFIX, telemetry.AUDIT),
                                   lambda s: audit.append(json.loads(s.payload.to_bytes())))
        time.sleep(0.5)

        def cli(*args: str) -> subprocess.CompletedProcess:
            return subprocess.run(
                [sys.executable, "-m", "commands.dashboard", "set", *args, "--prefix", PREFIX,
                 "--connect", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"],
                capture_output=True, text=True, timeout=60)

        refused = cli("weights", "position=-5")
        assert refused.returncode == 1
        assert "refused: weight position: -5.0 is out of range" in refused.stderr
        unknown = cli("weights", "stiffness=3")
        assert unknown.returncode == 1 and "unknown weight 'stiffness'" in unknown.stderr
        params = json.loads(list(session.get(telemetry.key_expr(PREFIX, "parameters")))[0]
                            .ok.payload.to_bytes())
        assert params["settings"]["weights"]["position"] == 400.0  # unchanged
        accepted = cli("weights", "position=300")
        assert accepted.returncode == 0, accepted.stderr
        time.sleep(0.3)
        params = json.loads(list(session.get(telemetry.key_expr(PREFIX, "parameters")))[0]
                            .ok.payload.to_bytes())
        assert params["settings"]["weights"]["position"] == 300.0
        time.sleep(0.3)
    finally:
        session.close()
        actuatord.terminate()
        actuatord.communicate(timeout=30)
    assert [a["accepted"] for a in audit] == [False, False, True]
    assert "out of range" in audit[0]["reason"] and audit[0]["request"] == "weights"


@pytest.mark.parametrize("args,needle", [
    (["set", "weights", "position"], "expected NAME=VALUE"),
    (["set", "reference", "{}", "{}"], "give one JSON object"),
])
def test_set_bad_usage_exits_2(args, needle):
    proc = subprocess.run([sys.executable, "-m", "commands.dashboard", *args], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2 and needle in proc.stderr


def test_zenoh_acl_lets_viewers_watch_and_only_operators_command(tmp_path):
    """The shipped ACL (docs/zenoh-acl.json5) enforced by actuatord's own Zenoh session."""
    from pathlib import Path

    import zenoh

    credentials = tmp_path / "credentials.txt"
    credentials.write_text("operator:op-secret\nviewer:view-secret\n")
    shipped = Path(__file__).parent.parent / "docs" / "zenoh-acl.json5"
    config = tmp_path / "acl.json5"
    config.write_text(shipped.read_text().replace('"credentials.txt"', json.dumps(
        str(credentials))))
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep", "--duration", "60",
         "--zenoh-config", str(config), "--listen", f"tcp/127.0.0.1:{port}",
         "--no-multicast-scouting"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def attempt(user: str, password: str) -> tuple[int, int, list]:
        c = zenoh.Config()
        c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
        session = zenoh.open(c)
        try:
            states = []
            session.declare_subscriber(f"{telemetry.DEFAULT_PREFIX}/state",
                                       lambda s: states.append(1))
            time.sleep(1.0)
            parameters = list(session.get(f"{telemetry.DEFAULT_PREFIX}/parameters", timeout=3))
            answers = [json.loads(r.ok.payload.to_bytes()) for r in session.get(
                f"{telemetry.DEFAULT_PREFIX}/weights", payload=json.dumps({"position": 350}),
                timeout=3) if r.ok is not None]
            return len(states), len(parameters), answers
        finally:
            session.close()

    try:
        assert "enabled" in proc.stdout.readline()
        viewer = attempt("viewer", "view-secret")
        operator = attempt("operator", "op-secret")
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
    assert viewer[0] > 100 and viewer[1] == 1  # reads telemetry and parameters
    assert viewer[2] == []  # but its command is never delivered
    assert operator[0] > 100 and operator[2] == [{"ok": True, "weights": {"position": 350}}]
