import subprocess
import sys

import pytest

from commands.model_options import parse_payload
from model.parameters import ModelFileError, default_model_path, load_model

DEFAULT = default_model_path().read_text()


def write(tmp_path, text):
    path = tmp_path / "elbow.toml"
    path.write_text(text)
    return path


def test_default_model_has_provenance_for_every_parameter():
    model = load_model()
    assert model.parameters.drive_gain == 5.0
    assert model.limits.current_max == 6.0
    assert model.limits.position_min == -2.35
    for name in model.parameters.__dataclass_fields__:
        if name != "effects":
            assert model.provenance[name].strip()
    assert model.parameters.effects.enabled() == []


@pytest.mark.parametrize("edit,message", [
    (("drive_gain = 5.0", "drive_gain = \"five\""), r"\[parameters\].drive_gain: expected a "
                                                     "finite number, got 'five'"),
    (("drive_gain = 5.0", "drive_gain = 5.0\nspring_gain = 1.0"),
     r"\[parameters\].spring_gain: unknown key"),
    (("link_inertia = 0.33\n", ""), r"\[parameters\].link_inertia: missing"),
    (("link_inertia = 0.33", "link_inertia = -0.33"), r"link_inertia: expected > 0"),
    (("drive_gain = 5.0", "drive_gain = nan"), r"drive_gain: expected a finite number"),
    (("[limits]", "[limitz]"), r"unknown table \[limitz\]"),
    (("drive_gain = 5.0", "drive_gain = = 5.0"), r"not valid TOML"),
    (("drive_gain = 5.0", "drive_gain = " + "9" * 401),
     r"drive_gain: expected a finite number, got an integer too large for a float"),
    (("drive_gain = 5.0", "drive_gain = " + "[" * 5000 + "]" * 5000),
     r"nested too deeply for a model file"),
    (("torque_offset_motor = 0.0", "torque_offset_motor = 1e12"),
     r"torque_offset_motor: 1e\+12 N.m; expected at most the drive's peak torque"),
])
def test_bad_model_files_name_file_and_field(tmp_path, edit, message):
    path = write(tmp_path, DEFAULT.replace(*edit, 1))
    with pytest.raises(ModelFileError, match=message) as info:
        load_model(path)
    assert str(path) in str(info.value)


def test_effect_tables_load_and_reach_the_dynamics(tmp_path):
    path = write(tmp_path, DEFAULT + """
[effects.stribeck]
breakaway_friction = 1.2
velocity = 0.04
provenance = "test"
""")
    model = load_model(path)
    assert model.parameters.effects.enabled() == ["stribeck"]
    assert model.provenance["effects.stribeck"] == "test"
    from model import dynamics

    assert model.parameters.packed()[dynamics.EFFECT_OFFSET["stribeck"]] == 1.2
    bad = write(tmp_path, DEFAULT + "\n[effects.backlash]\nwidth = 1\nprovenance = 'x'\n")
    with pytest.raises(ModelFileError, match=r"\[effects.backlash\]: unknown effect"):
        load_model(bad)


def test_a_model_file_that_is_not_utf8_names_the_file(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes(DEFAULT.replace("# TALOS", "# TALOS \xe9", 1).encode("latin-1"))
    with pytest.raises(ModelFileError, match="not UTF-8 text") as info:
        load_model(path)
    assert str(path) in str(info.value)
    with pytest.raises(ModelFileError, match="is a directory"):
        load_model(tmp_path)


def test_missing_model_file(tmp_path):
    with pytest.raises(ModelFileError, match="model file not found"):
        load_model(tmp_path / "nope.toml")


@pytest.mark.parametrize("args,needle", [
    (["--model", "{bad}"], "[parameters].drive_gain: expected a finite number"),
    (["--bus", "can:0"], "unknown interface 'can'"),
    (["--payload-mass", "5"], "without --payload-position"),
    (["--payload-mass", "5", "--payload-position", "0.05"], "expected X,Y"),
])
def test_sim_bus_bad_input_exits_2_with_one_line(tmp_path, args, needle):
    bad = write(tmp_path, DEFAULT.replace("drive_gain = 5.0", "drive_gain = 'x'"))
    args = [a.replace("{bad}", str(bad)) for a in args]
    if "--bus" not in args:
        args += ["--bus", "virtual:never-opened"]
    proc = subprocess.run([sys.executable, "-m", "commands.sim_bus", *args], capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], proc.stderr


def test_payload_adds_first_moments_and_inertia():
    params = load_model().parameters
    loaded = params.with_payload(parse_payload(30.0, "0,0.05"))
    assert loaded.first_moment_y == pytest.approx(params.first_moment_y + 1.5)
    assert loaded.first_moment_x == params.first_moment_x
    assert loaded.link_inertia == pytest.approx(params.link_inertia + 30 * 0.05**2)
