"""Record on the virtual drive (real processes), identify, and check against the drive's true
parameters; the same through CSV; bad input refused with one line."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from controller.loop import ControlLoop, LoopOptions
from controller.mpc import Mpc
from driver.clock import DriveClock
from driver.drive_group import single_joint
from model.parameters import load_model
from recorder.csv_io import write_csv
from recorder.reader import load_recording
from tests.conftest import holding_the_test_lock, virtual_pair

pytestmark = pytest.mark.subprocess  # runs the commands as processes

TRUE = load_model()
SHORT = ["--velocity-min", "0.8", "--steps", "3", "--no-progress"]  # 15 s of data each


def recorder(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "commands.recorder", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def identify(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "commands.identify", *args],
                          capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("recordings")
    no_load, load = folder / "noload.mcap", folder / "load.mcap"
    # two recorders on two cores: no real_time test beside them (`holding_the_test_lock`)
    with holding_the_test_lock(alone=False):
        jobs = [recorder("--exciting-trajectory", "--sim", "--lockstep", *SHORT, "-o",
                         str(no_load)),
                recorder("--exciting-trajectory", "--sim", "--lockstep", *SHORT, "--seed", "1",
                         "--payload-mass", "5", "--payload-position", "0,0.1", "-o", str(load))]
        for job in jobs:
            out, err = job.communicate(timeout=300)
            assert job.returncode == 0, err
            assert "real-time factor" in out
    return no_load, load


def check_identified(model_path: Path) -> None:
    identified = load_model(model_path).parameters
    truth = TRUE.parameters
    for name in ("drive_gain", "torque_sensor_gain", "first_moment_y"):
        assert getattr(identified, name) == pytest.approx(getattr(truth, name), rel=0.03), name
    for name in ("link_inertia", "motor_inertia", "viscous_friction_motor",
                 "viscous_friction_joint", "dry_friction_motor", "dry_friction_joint"):
        assert getattr(identified, name) == pytest.approx(getattr(truth, name), rel=0.15), name


def test_identify_from_mcap_recovers_the_drive_parameters(recordings, tmp_path):
    no_load, load = recordings
    model_path = tmp_path / "elbow.toml"
    proc = identify(str(no_load), str(load), "-o", str(model_path), "--plots", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    check_identified(model_path)
    assert "condition number" in proc.stdout and "rel. std" in proc.stdout
    model = load_model(model_path)
    assert model.provenance["drive_gain"].startswith(f"identified from {no_load}")
    assert 0 < model.std["drive_gain"] < 0.05
    assert len(list(tmp_path.glob("fit_*.png"))) == 2


def test_identify_from_csv_gives_the_same_model(recordings, tmp_path):
    no_load, load = recordings
    csvs = []
    for path in recordings:
        csv_path = tmp_path / (path.stem + ".csv")
        proc = subprocess.run([sys.executable, "-m", "commands.recorder", "export", str(path), "-o",
                               str(csv_path)], capture_output=True, text=True, timeout=60)
        assert proc.returncode == 0, proc.stderr
        csvs.append(csv_path)
    assert csvs[1].read_text().startswith("# payload_mass=5.0\n")
    proc = identify(*map(str, csvs), "-o", str(tmp_path / "from_csv.toml"))
    assert proc.returncode == 0, proc.stderr
    check_identified(tmp_path / "from_csv.toml")
    from_mcap = tmp_path / "from_mcap.toml"
    assert identify(str(no_load), str(load), "-o", str(from_mcap)).returncode == 0
    a = load_model(tmp_path / "from_csv.toml").parameters
    b = load_model(from_mcap).parameters
    assert a.effects == b.effects
    for name in vars(a):
        if name != "effects":
            assert getattr(a, name) == pytest.approx(getattr(b, name), rel=1e-3, abs=1e-4)


def test_controller_with_the_identified_model_tracks_as_well(recordings, tmp_path):
    model_path = tmp_path / "elbow.toml"
    assert identify(*map(str, recordings), "-o", str(model_path)).returncode == 0

    def tracking_rms(controller_model) -> float:
        with virtual_pair() as (_, drive):  # the drive always runs the true model
            drive.start()
            loop = ControlLoop(single_joint(drive), Mpc(controller_model),
                               LoopOptions(clock=DriveClock(), duration=3.0, keep_history=True))
            h = {k: np.array(v) for k, v in loop.run().history.items()}
        free = (h["t"] > 0.3) & (h["reference"] > -2.2)
        return float(np.sqrt(np.mean((h["position"][free] - h["reference"][free]) ** 2)))

    true_rms = tracking_rms(TRUE)
    identified_rms = tracking_rms(load_model(model_path))
    assert identified_rms < 1.1 * true_rms + 1e-4


def write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def sine_csv(tmp_path, name, seconds=10.0, amplitude=0.8, header="t,q,current,joint_torque",
             nan_row=None, payload=None, triangle=False, current_bias=-2.0):
    t = np.arange(0, seconds, 1e-3)
    wave = signal.sawtooth(2 * np.pi * 0.25 * t, 0.5) if triangle else np.sin(
        2 * np.pi * 0.3 * t)
    q = -1.2 + amplitude * wave
    lines = [f"# payload_mass={payload}", "# payload_position=0,0.1"] if payload else []
    lines.append(header)
    for k, tk in enumerate(t):
        current = "nan" if k == nan_row else f"{current_bias + np.sin(tk):.4f}"
        lines.append(f"{tk:.3f},{q[k]:.6f},{current},{-9 + np.cos(tk):.4f}")
    return write(tmp_path, name, "\n".join(lines) + "\n")


@pytest.mark.parametrize("case,needle", [
    ("no_motion", "nothing is excited"),
    ("too_short", "need at least 2.0 s"),
    ("nan", "column current: non-finite value at sample 7"),
    ("no_payload", "no payload given"),
    ("header", "header 't,position,current,joint_torque'"),
    ("truncated", "truncated MCAP"),
])
def test_bad_recordings_exit_2_with_one_line(tmp_path, recordings, case, needle):
    good = sine_csv(tmp_path, "good.csv")
    loaded = sine_csv(tmp_path, "loaded.csv", payload=5)
    files = {
        "no_motion": (sine_csv(tmp_path, "still.csv", amplitude=0.0), loaded),
        "too_short": (sine_csv(tmp_path, "short.csv", seconds=1.0), loaded),
        "nan": (sine_csv(tmp_path, "nan.csv", nan_row=7), loaded),
        "no_payload": (good, good),
        "header": (sine_csv(tmp_path, "h.csv", header="t,position,current,joint_torque"),
                   loaded),
        "truncated": (recordings[0], truncate(recordings[1], tmp_path)),
    }[case]
    proc = identify(*map(str, files), "-o", str(tmp_path / "out.toml"))
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], proc.stderr
    assert not (tmp_path / "out.toml").exists()


@pytest.mark.parametrize("case,needle", [
    ("same_file", "carry the same payload"),
    ("same_data", "are the same experiment"),
    ("payload_misplaced", "cannot scale the solution"),
    ("payload_on_axis", "adds no torque at the joint"),
])
def test_one_experiment_twice_or_a_payload_that_cannot_scale_is_refused(recordings, tmp_path,
                                                                         case, needle):
    no_load, load = map(str, recordings)
    args = {"same_file": [load, load],
            "same_data": [no_load, no_load, "--payload-mass", "5", "--payload-position",
                          "0,0.1"],
            # the payload hangs at (0, 0.1) m: claimed at (0, -0.1) m its torque has the
            # wrong sign and the solution comes out with negative gains and inertias
            "payload_misplaced": [no_load, load, "--payload-mass", "5", "--payload-position",
                                  "0,-0.1"],
            "payload_on_axis": [no_load, load, "--payload-mass", "5", "--payload-position",
                                "0,0"]}[case]
    out = tmp_path / "out.toml"
    proc = identify(*args, "-o", str(out))
    assert proc.returncode == 2, proc.stdout
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], proc.stderr
    assert not out.exists()


def truncate(path: Path, tmp_path: Path) -> Path:
    data = path.read_bytes()
    out = tmp_path / "truncated.mcap"
    out.write_bytes(data[: len(data) // 2 + 3])
    return out


def test_ill_conditioned_regressor_is_reported_with_its_condition_number(tmp_path):
    # back and forth at constant speed over a small range: viscous and dry friction are
    # collinear and the inertias barely excited
    still = sine_csv(tmp_path, "a.csv", amplitude=0.3, triangle=True)
    # the payload's torque shows in the current, so the two are not one experiment twice
    loaded = sine_csv(tmp_path, "b.csv", amplitude=0.3, payload=5, triangle=True,
                      current_bias=-3.0)
    proc = identify(str(still), str(loaded), "-o", str(tmp_path / "out.toml"))
    assert proc.returncode == 2
    assert "ill-conditioned (condition number" in proc.stderr, proc.stderr


def test_csv_round_trip_keeps_metadata_and_columns(tmp_path):
    recording = load_recording(sine_csv(tmp_path, "x.csv", payload=5))
    write_csv(recording, tmp_path / "y.csv")
    again = load_recording(tmp_path / "y.csv")
    assert again.metadata == {"payload_mass": "5", "payload_position": "0,0.1"}
    np.testing.assert_allclose(again.q, recording.q, atol=1e-6)
    assert again.payload().mass == 5.0
