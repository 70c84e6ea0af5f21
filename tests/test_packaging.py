"""What the wheel carries besides code: the robot files (found by name from any folder), the
layouts and the license the metadata declares."""

import glob
import tomllib
from pathlib import Path

import pytest

from robot.description import RobotFileError, load_robot

ROOT = Path(__file__).resolve().parent.parent
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def shipped_by(package: str) -> set[str]:
    """The files of a package folder its package-data patterns select (setuptools' globs)."""
    patterns = PROJECT["tool"]["setuptools"]["package-data"][package]
    return {name for pattern in patterns
            for name in glob.glob(pattern, root_dir=ROOT / package)}


def test_every_robot_file_and_model_and_both_layouts_are_package_data():
    robots = {str(path.relative_to(ROOT / "robots")) for path in (ROOT / "robots").rglob("*")
              if path.is_file() and path.suffix == ".toml"}
    assert robots and robots <= shipped_by("robots")
    assert {"elbow_layout.json", "elbow_experiment_layout.json"} <= shipped_by("dashboard")


def test_the_license_file_is_the_one_the_metadata_declares():
    assert PROJECT["project"]["license"] == "Apache-2.0"
    assert PROJECT["project"]["license-files"] == ["LICENSE"]
    text = (ROOT / "LICENSE").read_text()
    assert text.lstrip().startswith("Apache License\n                           Version 2.0")
    assert "END OF TERMS AND CONDITIONS" in text


def test_a_shipped_robot_is_found_by_name_from_any_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    robot = load_robot("talos_arm")
    assert robot.name == "talos_arm_left" and len(robot.joints) == 7
    assert len(load_robot("talos_32").joints) == 32
    with pytest.raises(RobotFileError, match="one of the shipped robots: talos_32, talos_arm"):
        load_robot("talos_leg")
    (tmp_path / "talos_arm").write_text("[robot]\n")  # a file of that name here wins
    with pytest.raises(RobotFileError, match="^talos_arm: "):
        load_robot("talos_arm")
