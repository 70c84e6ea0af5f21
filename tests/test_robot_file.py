"""Robot files: the shipped TALOS files load, every mistake is named, and a bus that cannot
carry its joints' cyclic traffic is refused with its load and the period that would fit."""

from pathlib import Path

import pytest

from protocol.bus_load import can_bus_load, can_frame_bits, ethercat_segment_load
from robot.description import RobotFileError, load_robot

ROBOTS = Path(__file__).resolve().parent.parent / "robots"
MODELS = ROBOTS / "models"


def test_can_frame_lengths_match_the_standard_figures():
    # 8 data bytes: 111 bits unstuffed, 135 with worst-case stuffing (Davis et al. 2007)
    assert can_frame_bits(8) == 111
    assert can_frame_bits(8, worst_case_stuffing=True) == 135
    assert can_frame_bits(0) == 47
    with pytest.raises(ValueError):
        can_frame_bits(9)


def test_two_joints_fit_a_1_mbit_bus_at_1_khz_and_three_do_not():
    two = can_bus_load("can0", [[6, 7, 8, 4]] * 2, 1_000_000, 1000, 100)
    three = can_bus_load("can0", [[6, 7, 8, 4]] * 3, 1_000_000, 1000, 100)
    assert 0.8 < two.load < 0.9 and two.fits
    assert three.load > 1.0 and not three.fits
    # the fastest period that fits is the one at which the load meets the budget
    slower = can_bus_load("can0", [[6, 7, 8, 4]] * 3, 1_000_000, three.fastest_period_us, 100)
    assert slower.fits and slower.load > 0.99 * slower.budget


def test_ethercat_carries_all_32_joints_in_one_frame():
    load = ethercat_segment_load("ethercat:eth1", [25] * 32, 1000)
    assert load.fits and load.load < 0.1


def test_shipped_robot_files_load():
    arm = load_robot(ROBOTS / "talos_arm.toml")
    assert len(arm.joints) == 7 and len(arm.buses()) == 4
    assert all(load.fits for load in arm.bus_loads())
    elbow = next(j for j in arm.joints if j.name == "arm_left_4_joint")
    assert elbow.model.limits.position_min == -2.35  # the paper's elbow
    whole = load_robot(ROBOTS / "talos_32.toml")
    assert len(whole.joints) == 32 and list(whole.buses()) == ["ethercat:eth1"]
    assert sorted(j.address for j in whole.joints) == list(range(32))
    for joint in (*arm.joints, *whole.joints):
        low, high = joint.reference.span()
        assert joint.model.limits.position_min <= low < high <= joint.model.limits.position_max
        for name, note in joint.model.provenance.items():
            assert note.strip(), f"{joint.name}: {name} has no provenance"


def _robot(tmp_path, joints: list[tuple[str, str]], extra: str = "") -> Path:
    """A robot file of elbow joints: (bus line(s), address line) per joint."""
    text = "[robot]\nname = \"test\"\nperiod_us = 1000\n" + extra
    for k, (bus, address) in enumerate(joints):
        text += f"\n[[joints]]\nname = \"j{k}\"\n{bus}\n{address}\n"
    path = tmp_path / "robot.toml"
    path.write_text(text)
    return path


def test_eight_joints_on_one_can_bus_are_refused_with_the_load(tmp_path):
    path = _robot(tmp_path, [('bus = "can0"', f"node_id = {k + 1}") for k in range(8)])
    with pytest.raises(RobotFileError, match=r"bus can0: 8 joints at 1000 us need 316 % of "
                                             r"1 Mbit/s .*fastest period that fits is 3530 us"):
        load_robot(path)


def test_the_same_joints_on_four_buses_or_on_ethercat_are_accepted(tmp_path):
    four = _robot(tmp_path, [(f'bus = "can{k // 2}"', f"node_id = {k % 2 + 1}")
                             for k in range(8)])
    assert len(load_robot(four).buses()) == 4
    ethercat = _robot(tmp_path, [('bus = "ethercat:eth1"', f"slave = {k}") for k in range(8)])
    assert len(load_robot(ethercat).joints) == 8


def test_a_slower_bitrate_is_budgeted(tmp_path):
    path = _robot(tmp_path, [('bus = "can0"', "node_id = 1")],
                  '\n[buses."can0"]\nbitrate = 250000\n')
    with pytest.raises(RobotFileError, match=r"bus can0: 1 joints at 1000 us need 178 % of "
                                             r"0.25 Mbit/s"):
        load_robot(path)


@pytest.mark.parametrize("joints,extra,message", [
    ([('bus = "can0"', "node_id = 1"), ('bus = "can0"', "node_id = 1")], "",
     r"joint 'j1': node id 1 is already used on can0"),
    ([('bus = "can0"', "slave = 1")], "", r"joint 'j0': a joint on CAN needs `node_id`"),
    ([('bus = "ethercat:eth1"', "node_id = 1")], "", r"a joint on EtherCAT needs `slave`"),
    ([('bus = "can0"', "node_id = 0")], "", r"joint 'j0'.node_id: expected an integer 1..127"),
    ([('bus = "can0"', "node_id = 1\nstiffness = 3")], "", r"joint 'j0'.stiffness: unknown key"),
    ([('bus = "nosuch:x"', "node_id = 1")], "", r"joint 'j0'.bus: bus spec 'nosuch:x'"),
    ([('bus = "can0"', 'node_id = 1\nmodel = "nope.toml"')], "",
     r"joint 'j0'.model: .*nope.toml: model file not found"),
    ([('bus = "can0"', "node_id = 1\nlimits = { position_min = -3.0 }")], "",
     r"limits.position_min: -3.0 must narrow the model's -2.35"),
    ([('bus = "can0"', "node_id = 1\nweights = { position = -1 }")], "",
     r"weights.position: expected >= 0"),
    ([('bus = "can0"', 'node_id = 1\nreference = { kind = "setpoint", position = -9.0 }')],
     "", r"joint 'j0'.reference: reference spans"),
    ([('bus = "can0"', "node_id = 1")], '\n[buses."can9"]\nbitrate = 500000\n',
     r'\[buses."can9"\]: no joint is on this bus'),
])
def test_mistakes_name_the_file_the_joint_and_the_field(tmp_path, joints, extra, message):
    path = _robot(tmp_path, joints, extra)
    with pytest.raises(RobotFileError, match=message) as caught:
        load_robot(path)
    assert str(caught.value).startswith(str(path))
    assert "\n" not in str(caught.value)


def test_unreadable_robot_files_are_refused_in_one_line(tmp_path):
    for text, message in ((b"[robot\n", "not valid TOML"), (b"\xff\xfe[robot]", "not valid TOML"),
                          (b"[robot]\nname = 'x'\n", r"joints: missing"),
                          (b"[robot]\nname='x'\nperiod_us=5\n[[joints]]\nname='a'\nbus='can0'\n"
                           b"node_id=1\n", r"period_us: expected an integer 100..100000")):
        path = tmp_path / "r.toml"
        path.write_bytes(text)
        with pytest.raises(RobotFileError, match=message):
            load_robot(path)
    with pytest.raises(RobotFileError, match="robot file not found"):
        load_robot(tmp_path / "missing.toml")
