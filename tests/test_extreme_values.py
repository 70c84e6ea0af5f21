"""Extreme values (issue 28 item 11): each is refused in one line naming its option, exit
code 2, before anything runs; the commands run in this process."""

import importlib
import json
import time

import pytest

from controller.reference import ReferenceError, reference_from_dict
from model.parameters import load_model
from tests.conftest import free_port

FAR = ["--payload-mass", "1", "--payload-position", "1e160,0"]


def run(capsys, command: str, argv: list[str]) -> tuple[int, str, str, float]:
    main = importlib.import_module(f"commands.{command}").main
    started = time.perf_counter()
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    elapsed = time.perf_counter() - started
    out, err = capsys.readouterr()
    return code, out, err, elapsed


CASES = [
    # a payload position past ~1e154 overflowed m (x^2 + y^2): OverflowError in five commands
    ("actuatord", ["--sim", *FAR, "--no-multicast-scouting"], "--payload-position 1e160,0"),
    ("sim_bus", ["--bus", "virtual:extreme", *FAR], "--payload-position 1e160,0"),
    ("recorder", ["--exciting-trajectory", "--sim", *FAR, "-o", "{tmp}/r.mcap"],
     "--payload-position 1e160,0"),
    ("identify", ["{tmp}/a.csv", "{tmp}/a.csv", *FAR, "-o", "{tmp}/m.toml"],
     "--payload-position 1e160,0"),
    # a trajectory that would never end, or exceed the model's velocity limit
    ("recorder", ["--exciting-trajectory", "--sim", "--velocity-min", "1e-300",
                  "--velocity-max", "1e-299", "-o", "{tmp}/r.mcap"], "--velocity-min 1e-300"),
    ("recorder", ["--exciting-trajectory", "--sim", "--velocity-max", "1e300", "-o",
                  "{tmp}/r.mcap"], "expected at most the model's velocity limit 5"),
    ("recorder", ["--sinusoid", "--sim", "--duration", "1e9", "-o", "{tmp}/r.mcap"],
     "--duration 1e+09 s"),
    # a hidden effect the drive could never overcome
    ("actuatord", ["--sim", "--truth-effect", "load_dependent_friction:coefficient=1e300",
                   "--no-multicast-scouting"], "expected at most the drive's peak torque"),
    ("sim_bus", ["--bus", "virtual:extreme", "--truth-effect",
                 "load_dependent_friction:coefficient=1e300"], "peak torque"),
    # --zenoh '' ran a trajectory on vcan0; drive options with --zenoh were ignored
    ("recorder", ["--zenoh", "", "-o", "{tmp}/r.mcap"], "--zenoh ''"),
    ("recorder", ["--zenoh", "x/**", "--sim", "-o", "{tmp}/r.mcap"], "--sim: --zenoh records"),
    ("recorder", ["--zenoh", "x/**", "--model", "{tmp}/m.toml", "-o", "{tmp}/r.mcap"],
     "--model: --zenoh records"),
    # a malformed endpoint Zenoh would ignore without a word
    ("actuatord", ["--sim", "--connect", "tcp/[::1"], "--connect 'tcp/[::1'"),
    ("dashboard", ["set", "weights", "position=300", "--listen", "tcp/127.0.0.1:99999"],
     "--listen"),
    ("recorder", ["--zenoh", "x/**", "--connect", "carrier-pigeon/home", "-o", "{tmp}/r.mcap"],
     "--connect"),
    # a reference whose kind is not a string: it was "internal error (TypeError)"
    ("actuatord", ["--sim", "--reference", '{"kind": ["setpoint"]}'], "reference kind"),
    ("actuatord", ["--sim", "--reference", '{"kind": "setpoint", "position": 1' + "0" * 400
                   + "}"], "setpoint.position: expected a finite number"),
]


@pytest.mark.parametrize("command,argv,needle", CASES,
                         ids=[f"{c}-{n[:30]}" for c, _, n in CASES])
def test_extreme_values_are_refused_in_one_line(capsys, tmp_path, command, argv, needle):
    (tmp_path / "a.csv").write_text("t,q,current,joint_torque\n0,-1,0,0\n0.001,-1,0,0\n")
    code, out, err, elapsed = run(capsys, command, [a.replace("{tmp}", str(tmp_path))
                                                    for a in argv])
    lines = err.strip().splitlines()
    assert code == 2, (code, out, err)
    assert len(lines) == 1 and "Traceback" not in err and needle in lines[0], err
    assert "enabled" not in out and "ready" not in out and elapsed < 5.0
    assert not (tmp_path / "r.mcap").exists()


def test_the_same_port_twice_is_refused_before_anything_listens(capsys):
    port = free_port()
    code, out, err, elapsed = run(capsys, "dashboard", [
        "foxglove", "--port", str(port), "--legacy-port", str(port),
        "--no-multicast-scouting"])
    assert code == 2 and "--legacy-port" in err and len(err.strip().splitlines()) == 1, err
    assert elapsed < 5.0


@pytest.mark.parametrize("spec,needle", [
    ({"kind": ["setpoint"]}, "reference kind ['setpoint']"),
    ({"kind": {"a": 1}}, "reference kind"),
    ({"kind": "setpoint", "position": 10 ** 400}, "setpoint.position"),
])
def test_unhashable_kinds_and_huge_integers_are_refused_not_internal_errors(spec, needle):
    with pytest.raises(ReferenceError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        reference_from_dict(json.loads(json.dumps(spec)), load_model().limits)
