"""An unexpected exception, in the loop's thread or any other, ends `actuatord` (one joint or
a robot) with every drive quick-stopped, one line on stderr and exit code 1 (issue 28 item 5:
it used to print a traceback and hang on the threads left behind, the drives switched on).
The bug is injected into the running command in this process."""

import pytest

from commands.actuatord import main

ROBOT = """[robot]
name = "pair"

[[joints]]
name = "j0"
bus = "can0"
node_id = 1

[[joints]]
name = "j1"
bus = "can0"
node_id = 2
"""
ARGS = ["--sim", "--lockstep", "--duration", "5", "--no-multicast-scouting"]


def failing_after(original, calls: int, exc: Exception):
    """`original` that raises `exc` on its `calls`-th call."""
    count = [0]

    def wrapper(*args, **kwargs):
        count[0] += 1
        if count[0] == calls:
            raise exc
        return original(*args, **kwargs)

    return wrapper


@pytest.fixture
def robot_devices(monkeypatch):
    """The virtual drives of every robot actuatord opens, read back after the run."""
    import robot.wiring as wiring

    opened = []
    real = wiring.open_robot

    def spy(*args, **kwargs):
        connection = real(*args, **kwargs)
        opened.append(connection.devices)
        return connection

    monkeypatch.setattr(wiring, "open_robot", spy)
    return opened


def _check_ended(capsys, code: int, needle: str) -> str:
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 1, (out, err)
    assert len(lines) == 1 and needle in lines[0], err
    assert "Traceback" not in err + out
    return out


@pytest.mark.timeout(120)
@pytest.mark.parametrize("where", ["loop", "thread"])
def test_a_robot_run_quick_stops_every_drive_and_exits_1(capsys, tmp_path, monkeypatch,
                                                         robot_devices, where):
    from controller.loop import ControlLoop
    from controller.telemetry import TelemetryPublisher
    from protocol.cia402 import State

    if where == "loop":
        monkeypatch.setattr(ControlLoop, "_robot_view", failing_after(
            ControlLoop._robot_view, 50, TypeError("injected bug")))
        needle = "internal error: TypeError: injected bug"
    else:
        monkeypatch.setattr(TelemetryPublisher, "_drain", failing_after(
            TelemetryPublisher._drain, 3, RuntimeError("injected bug")))
        needle = "thread telemetry: internal error: RuntimeError: injected bug"
    path = tmp_path / "pair.toml"
    path.write_text(ROBOT)
    out = _check_ended(capsys, main(["--robot", str(path), *ARGS]), needle)
    stopped = next(line for line in out.splitlines() if "quick stop:" in line)
    assert "j0 quick stop active" in stopped and "j1 quick stop active" in stopped, stopped
    (devices,) = robot_devices
    assert all(device.state is not State.OPERATION_ENABLED for device in devices.values())
    assert all(device.cycle_count < 5000 for device in devices.values())  # ended early


@pytest.mark.timeout(120)
def test_a_single_joint_run_ends_in_one_line_and_exit_1(capsys, monkeypatch):
    from controller.loop import ControlLoop

    monkeypatch.setattr(ControlLoop, "_joint_view", failing_after(
        ControlLoop._joint_view, 50, KeyError("injected")))
    out = _check_ended(capsys, main(ARGS), "internal error: KeyError")
    assert "ran 5" not in out


@pytest.mark.parametrize("command,patched,argv", [
    ("identify", "load_model_option", ["a.csv", "b.csv", "-o", "{tmp}/m.toml"]),
    ("model_gap", "load_model_option", ["a.csv", "--model", "m.toml"]),
    ("recorder", "load_recording", ["export", "a.mcap", "-o", "{tmp}/a.csv"]),
    ("sim_bus", "load_model_option", ["--bus", "virtual:bug"]),
    ("dashboard", "open_session", ["set", "weights", "position=300"]),
])
def test_every_command_turns_a_bug_into_one_line_and_exit_1(capsys, monkeypatch, tmp_path,
                                                           command, patched, argv):
    import importlib

    module = importlib.import_module(f"commands.{command}")

    def bug(*args, **kwargs):
        raise RuntimeError("injected bug")

    monkeypatch.setattr(module, patched, bug)
    code = module.main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1, err
    assert "internal error: RuntimeError: injected bug" in lines[0] and "Traceback" not in err
