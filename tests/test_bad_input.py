"""Every command refuses bad input the same way: exit code 2, one line on stderr naming the
option or file and what was expected, no traceback, and nothing done before the refusal (no
drive touched, no output file left behind). Each case runs the command as a user would."""

import socket
import subprocess
import sys
from pathlib import Path

import pytest

from model.parameters import default_model_path

pytestmark = pytest.mark.subprocess  # runs the commands as processes

SIM = ["--sim", "--no-multicast-scouting"]
CSV = "# payload_mass=0\nt,q,current,joint_torque\n0.000,-1.0,0.1,0.2\n0.001,-1.0,0.1,0.2\n"


def run(module: str, args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", f"commands.{module}", *args],
                          capture_output=True, text=True, timeout=120)


@pytest.fixture
def files(tmp_path):
    """A tiny valid CSV recording, a binary file, a folder, and where outputs would go."""
    recording = tmp_path / "rec.csv"
    recording.write_text(CSV)
    binary = tmp_path / "blob.csv"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff\xfe" * 50)
    folder = tmp_path / "folder"
    folder.mkdir()
    default = default_model_path().read_text()
    models = {"digits": default.replace("drive_gain = 5.0", "drive_gain = " + "9" * 401),
              "deep": default.replace("drive_gain = 5.0",
                                      "drive_gain = " + "[" * 5000 + "]" * 5000),
              "offset": default.replace("torque_offset_motor = 0.0",
                                        "torque_offset_motor = 1e12")}
    for name, text in models.items():
        (tmp_path / f"{name}.toml").write_text(text)
    (tmp_path / "latin1.toml").write_bytes(default.replace("# TALOS", "# TALOS \xe9", 1)
                                           .encode("latin-1"))
    return {"rec": str(recording), "bin": str(binary), "dir": str(folder),
            "out": str(tmp_path / "out.mcap"), "tmp": str(tmp_path)}


CASES = [
    # actuatord
    ("actuatord", [*SIM, "--node-id", "0"], "--node-id"),
    ("actuatord", [*SIM, "--node-id", "200"], "--node-id"),
    ("actuatord", [*SIM, "--inject-fault", "silent@nan"], "--inject-fault"),
    ("actuatord", [*SIM, "--inject-fault", "silent@inf"], "--inject-fault"),
    ("actuatord", [*SIM, "--prefix", ""], "--prefix"),
    ("actuatord", [*SIM, "--prefix", "a//b"], "--prefix"),
    ("actuatord", [*SIM, "--prefix", "a/$*/b"], "--prefix"),
    ("actuatord", [*SIM, "--plot", "/proc/xx"], "--plot"),
    ("actuatord", [*SIM, "--payload-mass", "1e300", "--payload-position", "0,0.05"],
     "--payload-mass"),
    ("actuatord", [*SIM, "--truth-effect", "position_ripple:amplitude=1e300"],
     "--truth-effect"),
    ("actuatord", [*SIM, "--seed", "-1"], "--seed"),
    ("actuatord", [*SIM, "--horizon", "1000000"], "--horizon"),
    ("actuatord", [*SIM, "--horizon", "2", "--dt", "0.1"], "--dt"),
    ("actuatord", [*SIM, "--period-us", "100000"], "--period-us"),
    ("actuatord", [*SIM, "--reference", "{"], "--reference"),
    ("actuatord", [*SIM, "--duration", "nan"], "--duration"),
    ("actuatord", [*SIM, "--weight", "position=nan"], "--weight"),
    ("actuatord", [*SIM, "--can-log", "/nonexistent/x.log"], "--can-log"),
    ("actuatord", [*SIM, "--can-log", "{tmp}/x.pcap"], "--can-log"),
    ("actuatord", ["--bus", "can:0"], "unknown interface 'can'"),
    ("actuatord", [*SIM, "--bus", "virtual:x"], "--sim"),
    ("actuatord", ["--bus", "virtual:x", "-i", "virtual"], "--bus"),
    ("actuatord", [*SIM, "--model", "{tmp}/digits.toml"], "digits.toml"),
    ("actuatord", [*SIM, "--model", "{tmp}/deep.toml"], "deep.toml"),
    ("actuatord", [*SIM, "--model", "{tmp}/latin1.toml"], "latin1.toml"),
    ("actuatord", [*SIM, "--model", "{tmp}/offset.toml"], "torque_offset_motor"),
    # sim-bus
    ("sim_bus", ["--bus", "virtual:x", "--inject-fault", "silent@nan"], "--inject-fault"),
    ("sim_bus", ["--bus", "virtual:x", "--inject-fault", "silent@inf"], "--inject-fault"),
    ("sim_bus", ["--bus", "virtual:x", "--initial-position", "nan"], "--initial-position"),
    ("sim_bus", ["--bus", "virtual:x", "--initial-position", "3"], "--initial-position"),
    ("sim_bus", ["--bus", "virtual:x", "--seed", "-1"], "--seed"),
    ("sim_bus", ["--bus", "virtual:x", "--current-noise", "nan"], "--current-noise"),
    ("sim_bus", ["--bus", "virtual:x", "--node-id", "0"], "--node-id"),
    ("sim_bus", ["--bus", "virtual:x", "--payload-mass", "1e300", "--payload-position", "0,1"],
     "--payload-mass"),
    # recorder
    ("recorder", ["--exciting-trajectory", *SIM, "-o", "/nonexistent/x.mcap"],
     "/nonexistent/x.mcap"),
    ("recorder", ["--exciting-trajectory", *SIM, "--node-id", "0", "-o", "{out}"],
     "--node-id"),
    ("recorder", ["--exciting-trajectory", *SIM, "--seed", "-1", "-o", "{out}"], "--seed"),
    ("recorder", ["--exciting-trajectory", *SIM, "-o", "{dir}"], "is a directory"),
    ("recorder", ["--sinusoid", *SIM, "--duration", "nan", "-o", "{out}"], "--duration"),
    ("recorder", ["--sinusoid", *SIM, "--duration", "-5", "-o", "{out}"], "--duration"),
    ("recorder", ["--zenoh", "a//b", "-o", "{out}"], "--zenoh"),
    ("recorder", ["--zenoh", "x/**", "--can-log", "{tmp}/x.log", "-o", "{out}"], "--can-log"),
    ("recorder", ["export", "{bin}", "-o", "{tmp}/x.csv"], "blob.csv"),
    ("recorder", ["export", "{dir}", "-o", "{tmp}/x.csv"], "folder"),
    ("recorder", ["export", "{rec}", "-o", "/nonexistent/x.csv"], "/nonexistent/x.csv"),
    # identify
    ("identify", ["{rec}", "{rec}", "-o", "/nonexistent/x.toml"], "/nonexistent/x.toml"),
    ("identify", ["{rec}", "{rec}", "-o", "{tmp}/m.toml", "--cutoff", "0"], "--cutoff"),
    ("identify", ["{rec}", "{rec}", "-o", "{tmp}/m.toml", "--cutoff", "-5"], "--cutoff"),
    ("identify", ["{rec}", "{rec}", "-o", "{tmp}/m.toml", "--cutoff", "nan"], "--cutoff"),
    ("identify", ["{rec}", "{rec}", "-o", "{tmp}/m.toml", "--plots", "/proc/xx"], "--plots"),
    # model-gap
    ("model_gap", ["{rec}", "--model", str(default_model_path()), "--report",
                   "/nonexistent/gap.json"], "--report"),
    ("model_gap", ["{rec}", "--model", str(default_model_path()), "--plots", "/proc/xx"],
     "--plots"),
    # dashboard
    ("dashboard", ["foxglove", "--port", "99999", "--no-multicast-scouting"], "--port"),
    ("dashboard", ["foxglove", "--port", "{busy}", "--no-multicast-scouting"], "--port"),
    ("dashboard", ["tui", "--prefix", "a//b", "--no-multicast-scouting"], "--prefix"),
]


@pytest.mark.parametrize("module,args,needle", CASES,
                         ids=[f"{m}:{' '.join(a)}" for m, a, _ in CASES])
def test_bad_input_is_one_line_and_exit_2(files, module, args, needle):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        values = {**files, "busy": str(busy.getsockname()[1])}
        for name, value in values.items():
            args = [a.replace(f"{{{name}}}", value) for a in args]
        before = sorted(Path(files["tmp"]).rglob("*"))
        proc = run(module, args)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr and needle in lines[0], lines[0]
    assert lines[0].startswith(f"{module.replace('_', '-')}") and ": error: " in lines[0]
    assert "enabled" not in proc.stdout and "ready" not in proc.stdout  # no drive touched
    assert sorted(Path(files["tmp"]).rglob("*")) == before  # no file created
