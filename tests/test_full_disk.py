"""A full disk (issue 28 item 9): recorder, identify and model-gap end in one line naming the
file, exit code 1, no traceback; a recording cut by the full disk stays repairable, and a model,
report or CSV is written whole or not at all. The disk is a small tmpfs mounted for the test
(root), so the error is the kernel's own ENOSPC at whatever moment it comes."""

import importlib
import math
import os
import subprocess
from pathlib import Path

import pytest

from model.gap.report import GapResult
from model.identify import Identified
from model.parameters import default_model_path, load_model
from recorder.reader import load_recording

pytestmark = [pytest.mark.root,
              pytest.mark.skipif(os.geteuid() != 0, reason="mounting a tmpfs needs root")]
CSV = "t,q,current,joint_torque\n" + "".join(f"{k / 1000:.3f},-1.0,0.1,0.2\n"
                                              for k in range(3000))


@pytest.fixture
def disk(tmp_path):
    """Mount a tmpfs of `size` bytes (the folder is returned)."""
    mounted = []

    def mount(size: int) -> Path:
        folder = tmp_path / f"disk{len(mounted)}"
        folder.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                       check=True)
        mounted.append(folder)
        return folder

    yield mount
    for folder in mounted:
        subprocess.run(["umount", "-l", str(folder)], check=False)


def fill(folder: Path) -> None:
    """Leave no free block on the tmpfs."""
    with open(folder / "filler", "wb", buffering=0) as fh:
        try:
            while True:
                fh.write(b"\0" * 4096)
        except OSError:
            pass


def run(capsys, command: str, argv: list[str]) -> tuple[int, str, str]:
    main = importlib.import_module(f"commands.{command}").main
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "No space left on device" in lines[0], lines[0]
    return lines[0]


@pytest.mark.timeout(300)
@pytest.mark.parametrize("size", [8192, 40 * 1024, 100 * 1024, 300 * 1024])
def test_recorder_on_a_full_disk_is_one_line_and_the_file_stays_repairable(
        capsys, disk, tmp_path, size):
    output = disk(size) / "run.mcap"
    code, out, err = run(capsys, "recorder", ["--exciting-trajectory", "--sim", "--lockstep",
                                              "--no-progress", "-o", str(output)])
    assert code == 1, (out, err)
    line = one_line(err)
    assert str(output) in line and "recorder repair" in line
    if not output.exists():  # nothing was flushed: the recording was discarded
        return
    repaired = tmp_path / "repaired.mcap"
    code, out, err = run(capsys, "recorder", ["repair", str(output), "-o", str(repaired)])
    assert code == 0, err
    if size >= 100 * 1024:  # room for chunks of samples: they are kept
        assert len(load_recording(repaired)) > 0


def test_recorder_export_and_repair_on_a_full_disk_leave_no_partial_file(capsys, disk,
                                                                          tmp_path):
    source = tmp_path / "rec.csv"
    source.write_text(CSV)
    full = disk(64 * 1024)
    fill(full)
    code, out, err = run(capsys, "recorder", ["export", str(source), "-o", str(full / "x.csv")])
    assert code == 1 and str(full / "x.csv") in one_line(err)
    assert sorted(p.name for p in full.iterdir()) == ["filler"]


def _identified() -> Identified:
    parameters = load_model().parameters
    return Identified(parameters, {"drive_gain": 1.0}, {}, 36.0, 0.5, 0.5, 1000, {})


def test_identify_on_a_full_disk_is_one_line_and_leaves_no_file(capsys, disk, tmp_path,
                                                                 monkeypatch):
    import model.identify

    # commands.identify imports identify once its arguments are parsed (a quick --help)
    monkeypatch.setattr(model.identify, "identify", lambda *args: _identified())
    recording = tmp_path / "rec.csv"
    recording.write_text(CSV)
    full = disk(64 * 1024)
    fill(full)
    output = full / "m.toml"
    code, out, err = run(capsys, "identify", [str(recording), str(recording),
                                              "--payload-mass", "1", "--payload-position",
                                              "0,0.05", "-o", str(output)])
    assert code == 1 and str(output) in one_line(err)
    assert sorted(p.name for p in full.iterdir()) == ["filler"]


def test_model_gap_on_a_full_disk_is_one_line(capsys, disk, tmp_path, monkeypatch):
    import model.gap

    nan = math.nan
    result = GapResult(effects=[], rmsd_before=1.0, rmsd_after=1.0, sim_rmsd_before=0.1,
                       sim_rmsd_after=0.1, rmsd_sensor_before=nan, rmsd_sensor_after=nan,
                       horizon=0.5, candidates={}, steps=[], discrimination=[],
                       instruments={}, held_out_rmsd=1.0, unexplained={}, correction=None,
                       parameters=load_model().parameters, localisation_before={},
                       localisation_after={}, residuals={}, traces_before=[],
                       traces_after=[])
    # commands.model_gap imports find_gap once its arguments are parsed (a quick --help)
    monkeypatch.setattr(model.gap, "find_gap", lambda *args: result)
    recording = tmp_path / "rec.csv"
    recording.write_text(CSV)
    full = disk(64 * 1024)
    fill(full)
    report = full / "gap.json"
    code, out, err = run(capsys, "model_gap", [str(recording), "--model",
                                               str(default_model_path()), "--report",
                                               str(report)])
    assert code == 1 and str(report) in one_line(err)
    assert sorted(p.name for p in full.iterdir()) == ["filler"]
