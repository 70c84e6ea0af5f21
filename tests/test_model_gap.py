"""model-gap on recordings in which an effect is hidden in the virtual drive: the workflow is
given recordings and a baseline model only, never the effect's name or parameters."""

import json
import subprocess
import sys
import tomllib
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import tomli_w

from controller.mpc import Mpc
from model import dynamics
from model.parameters import load_model

pytestmark = pytest.mark.subprocess  # runs the commands as processes

HIDDEN = {
    "stribeck": "stribeck:breakaway_friction=1.5,velocity=0.05",
    "position_ripple": "position_ripple:amplitude=0.6,spatial_frequency=8,phase=0.3",
    "load_dependent_friction": "load_dependent_friction:coefficient=0.1",
    "none": None,
}
SHORT = ["--velocity-min", "0.8", "--steps", "3", "--no-progress"]


def run(module: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True,
                          text=True, timeout=600)


def recording_jobs(folder: Path, truth: str | None) -> tuple[dict[str, Path], list[list[str]]]:
    """Two identification runs and a slow sinusoid, with 19-bit encoder and sensor noise, in
    closed loop on the virtual drive (then the baseline is identified without any effect)."""
    effect = ["--truth-effect", truth] if truth else []
    common = ["--sim", "--lockstep", "--no-progress", *effect]
    files = {k: folder / f"{k}.mcap" for k in ("noload", "load", "sinusoid")}
    files["baseline"] = folder / "baseline.toml"
    return files, [
        ["--exciting-trajectory", *common, *SHORT, "-o", str(files["noload"])],
        ["--exciting-trajectory", *common, *SHORT, "--seed", "1", "--payload-mass", "5",
         "--payload-position", "0,0.1", "-o", str(files["load"])],
        ["--sinusoid", *common, "--duration", "20", "--seed", "2", "-o",
         str(files["sinusoid"])]]


@pytest.fixture(scope="module")
def scenarios(tmp_path_factory) -> dict[str, dict[str, Path]]:
    """Every scenario's recordings, two at a time (two cores), then each baseline."""
    out, jobs = {}, []
    for name, truth in HIDDEN.items():
        out[name], more = recording_jobs(tmp_path_factory.mktemp(name), truth)
        jobs += more
    with ThreadPoolExecutor(2) as pool:
        for proc in pool.map(lambda job: run("commands.recorder", *job), jobs):
            assert proc.returncode == 0, proc.stderr
        identified = pool.map(lambda files: run(
            "commands.identify", str(files["noload"]), str(files["load"]), "-o",
            str(files["baseline"])), out.values())
        for proc in identified:
            assert proc.returncode == 0, proc.stderr
    return out


def model_gap(files: dict[str, Path], *extra: str) -> tuple[subprocess.CompletedProcess, dict]:
    report = files["baseline"].parent / "gap.json"
    proc = run("commands.model_gap", str(files["noload"]), str(files["load"]),
               str(files["sinusoid"]), "--model", str(files["baseline"]), "--report",
               str(report), *extra)
    return proc, json.loads(report.read_text()) if report.exists() else {}


@pytest.mark.parametrize("effect", ["stribeck", "position_ripple", "load_dependent_friction"])
def test_hidden_effect_is_named_and_the_gap_shrinks(scenarios, effect, tmp_path):
    files = scenarios[effect]
    improved = tmp_path / "improved.toml"
    proc, report = model_gap(files, "-o", str(improved), "--plots", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    assert report["effect"] == effect
    assert report["rmsd_after"] <= 0.6 * report["rmsd_before"]
    assert report["sim_rmsd_after"] <= 0.6 * report["sim_rmsd_before"]
    assert report["model"] == str(improved)
    model = load_model(improved)
    assert model.parameters.effects.enabled() == [effect]
    assert model.provenance[f"effects.{effect}"].startswith("model-gap on")
    assert len(list(tmp_path.glob("*.png"))) == 3
    # the improved model reaches the controller's dynamics
    mpc = Mpc(model)
    assert mpc.dynamics_parameters[dynamics.EFFECT_OFFSET[effect]] != 0.0


def test_hidden_effect_parameters_come_back(scenarios, tmp_path):
    improved = tmp_path / "stribeck.toml"
    model_gap(scenarios["stribeck"], "-o", str(improved))
    effects = load_model(improved).parameters.effects.section("stribeck")
    assert effects["breakaway_friction"] == pytest.approx(1.5, rel=0.2)
    assert effects["velocity"] == pytest.approx(0.05, rel=0.3)
    improved = tmp_path / "ripple.toml"
    model_gap(scenarios["position_ripple"], "-o", str(improved))
    effects = load_model(improved).parameters.effects.section("position_ripple")
    assert effects["spatial_frequency"] == pytest.approx(8.0, abs=0.1)
    assert effects["amplitude"] == pytest.approx(0.6, rel=0.1)


def test_clean_data_gives_none_and_leaves_the_model_alone(scenarios, tmp_path):
    files = scenarios["none"]
    improved = tmp_path / "improved.toml"
    proc, report = model_gap(files, "-o", str(improved))
    assert proc.returncode == 0, proc.stderr
    assert report["effect"] == "none"
    assert report["rmsd_after"] == report["rmsd_before"]
    assert report["model"] == str(files["baseline"])
    assert not improved.exists()


def test_a_model_of_another_actuator_is_refused_with_a_clear_message(scenarios, tmp_path):
    files = dict(scenarios["none"])
    text = files["baseline"].read_text()
    other = tmp_path / "other.toml"
    other.write_text(_scaled(text, "first_moment_y", 2.5))  # a much heavier link
    files["baseline"] = other
    proc, _ = model_gap(files)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "does not fit these recordings" in lines[0]


def _scaled(text: str, key: str, factor: float) -> str:
    doc = tomllib.loads(text)
    doc["parameters"][key] *= factor
    return tomli_w.dumps(doc)


def test_bad_recording_is_refused(tmp_path, scenarios):
    bad = tmp_path / "bad.csv"
    bad.write_text("time,q,current,joint_torque\n0,0,0,0\n")
    proc = run("commands.model_gap", str(bad), "--model", str(scenarios["none"]["baseline"]))
    assert proc.returncode == 2
    assert "header" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
