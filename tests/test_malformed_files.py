"""Malformed dictionaries, descriptions and models (issue 28 item 10): a generator derives
broken EDS, ESI, model and robot files from the shipped ones, one defect each, and every case
is refused by the command that reads it in one line naming the file, exit code 2, with nothing
enabled (in this process: a case that got through would start the drive and print
"enabled", or reach the EtherCAT interface, which does not exist, and exit 1). Valid variants
(a UTF-8 BOM, CRLF line ends, an EDS without a default for 0x608F) are accepted."""

import importlib
import re
from pathlib import Path

import pytest

from model.parameters import Payload, default_model_path, load_model
from protocol import eds_path, esi_path, objects

EDS = eds_path().read_text()
ESI = esi_path().read_text()
MODEL = default_model_path().read_text()
NO_ETHERCAT = ["--bus", "ethercat:nonexistent0"]  # reaching the interface would be exit 1


def _set(text: str, section: str, key: str, value: str) -> str:
    """The EDS with `key` of `[section]` set to `value` (the key must be there)."""
    pattern = re.compile(rf"(\[{re.escape(section)}\]\n(?:[^\[]*?\n)?){key}=[^\n]*")
    edited, count = pattern.subn(lambda m: f"{m.group(1)}{key}={value}", text, count=1)
    assert count == 1, (section, key)
    return edited


def malformed_eds() -> dict[str, tuple[str, str]]:
    """name -> (EDS text, what the refusal says)."""
    return {
        "unknown DataType": (_set(EDS, "6041", "DataType", "0x0099"), "DataType=0x0099"),
        "DataType not a number": (_set(EDS, "6041", "DataType", "word"), "DataType=word"),
        "default above UNSIGNED16": (_set(EDS, "6041", "DefaultValue", "99999999"),
                                     "expected 0..65535"),
        "negative UNSIGNED32 default": (_set(EDS, "608Fsub1", "DefaultValue", "-5"),
                                        "expected 0..4294967295"),
        "inverted position window": (_set(EDS, "607Dsub2", "DefaultValue", "-300000"),
                                     "min -204435 >= max -300000"),
        "zero encoder resolution": (_set(EDS, "608Fsub1", "DefaultValue", "0"),
                                    "encoder increments"),
        "zero rated torque": (_set(EDS, "6076", "DefaultValue", "0"), "rated torque"),
        "no section header": ("ParameterName=x\n" + EDS, "line 1: expected a [section]"),
        "duplicate section": (EDS + "\n[6041]\nParameterName=again\n", "6041"),
        "line without =": (EDS.replace("[6041]\n", "[6041]\ngarbage line\n", 1),
                           "expected KEY=VALUE"),
        "binary": ("\x00\x01\x02" * 100, "not a valid EDS"),
    }


def malformed_esi() -> dict[str, tuple[str, str]]:
    """name -> (ESI text, what the refusal says): the issue's out-of-range values and more."""
    entry = ("          <Entry>\n            <Index>#x2001</Index>\n            <SubIndex>0"
             "</SubIndex>\n            <BitLen>16</BitLen>\n            <Name>Extra</Name>\n"
             "            <DataType>INT</DataType>\n          </Entry>\n")
    tx_end = ESI.index("        </TxPdo>")
    return {
        "vendor id over 32 bits": (ESI.replace("<Id>#x00000000</Id>", "<Id>#x1FFFFFFFF</Id>"),
                                   "Vendor/Id"),
        "negative product code": (ESI.replace('ProductCode="#x00000402"', 'ProductCode="-1"'),
                                  "ProductCode"),
        "huge revision": (ESI.replace('RevisionNo="#x00010000"', 'RevisionNo="99999999999"'),
                          "RevisionNo"),
        "EEPROM of 0 bytes": (ESI.replace("<ByteSize>2048</ByteSize>", "<ByteSize>0</ByteSize>"),
                              "Eeprom/ByteSize"),
        "EEPROM of 1 GB": (ESI.replace("<ByteSize>2048</ByteSize>",
                                       "<ByteSize>1000000000</ByteSize>"), "Eeprom/ByteSize"),
        "EEPROM too small for the SII": (ESI.replace("<ByteSize>2048</ByteSize>",
                                                     "<ByteSize>128</ByteSize>"), "SII image"),
        "EEPROM not in KiBit steps": (ESI.replace("<ByteSize>2048</ByteSize>",
                                                  "<ByteSize>2000</ByteSize>"), "multiple of 128"),
        "SM address past the ESC": (ESI.replace('StartAddress="#x1100"',
                                                'StartAddress="#x10000"'), "StartAddress"),
        "SM window past the ESC": (ESI.replace('StartAddress="#x1180"',
                                               'StartAddress="#xFFF0" DefaultSize="64" '
                                               'MaxSize="64"'), "64 KiB"),
        "SM size over 16 bits": (ESI.replace('DefaultSize="128" StartAddress="#x1000"',
                                             'DefaultSize="#x20000" StartAddress="#x1000"'),
                                 "DefaultSize"),
        "control byte over 8 bits": (ESI.replace('ControlByte="#x26"', 'ControlByte="#x1FF"'),
                                     "ControlByte"),
        "zero bit length": (ESI.replace("<BitLen>16</BitLen>", "<BitLen>0</BitLen>", 1),
                            "BitLen"),
        "huge bit length": (ESI.replace("<BitLen>32</BitLen>", "<BitLen>4096</BitLen>", 1),
                            "BitLen"),
        "bit length not the type's": (ESI.replace("<BitLen>32</BitLen>", "<BitLen>16</BitLen>",
                                                  1), "expected 32 for DINT"),
        "9 PDO entries": (ESI[:tx_end] + entry * 3 + ESI[tx_end:], "at most 8"),
        "PDO on a missing SM": (ESI.replace('Sm="3"', 'Sm="7"'), "Sm=7"),
        "PDO index over 16 bits": (ESI.replace("<Index>#x1A00</Index>",
                                               "<Index>#x1FFFFF</Index>"), "Index"),
        "TxPDO at an RxPDO index": (ESI.replace("<Index>#x1A00</Index>",
                                                "<Index>#x1601</Index>"), "0x1A00..0x1BFF"),
        "subindex over 8 bits": (ESI.replace("<SubIndex>0</SubIndex>",
                                             "<SubIndex>300</SubIndex>", 1), "SubIndex"),
        "ConfigData not hex": (ESI.replace("<ConfigData>0500000000000000</ConfigData>",
                                           "<ConfigData>zz</ConfigData>"), "ConfigData"),
        "not XML": (ESI[:200], "not XML"),
    }


def malformed_models() -> dict[str, tuple[str, str]]:
    """name -> (model TOML, what the refusal says)."""
    def edit(old: str, new: str) -> str:
        assert old in MODEL
        return MODEL.replace(old, new)

    return {
        "K_j 1e-300": (edit("torque_sensor_gain = 1.015", "torque_sensor_gain = 1e-300"),
                       "torque_sensor_gain"),
        "drive gain 1e300": (edit("drive_gain = 5.0", "drive_gain = 1e300"), "drive_gain"),
        "inertia 1e-300": (edit("link_inertia = 0.33", "link_inertia = 1e-300"),
                           "link_inertia"),
        "friction 1e300": (edit("viscous_friction_motor = 0.6",
                                "viscous_friction_motor = 1e300"), "viscous_friction_motor"),
        "position range 1e300": (edit("position_min = -2.35", "position_min = -1e300"),
                                 "position_min"),
        "nan": (edit("drive_gain = 5.0", "drive_gain = nan"), "finite"),
        "inverted limits": (edit("position_min = -2.35", "position_min = 1.0"),
                            "position_min must be below"),
        "velocity_max below the default reference's peak": (
            edit("velocity_max = 5.0", "velocity_max = 0.01"), "peak velocity"),
        "range narrower than the default reference": (
            edit("position_min = -2.35", "position_min = -1e-12"), "reference spans"),
        "not TOML": (MODEL.replace("[parameters]", "[parameters", 1), "not valid TOML"),
    }


def robot_neighbours(tmp: Path) -> None:
    """The EDS and model files the malformed robot files name, beside them."""
    (tmp / "bad.eds").write_text(malformed_eds()["unknown DataType"][0])
    (tmp / "tiny.toml").write_text(malformed_models()["K_j 1e-300"][0])


def malformed_robots() -> dict[str, tuple[str, str]]:
    """name -> (robot TOML, what the refusal says), its files from `robot_neighbours`."""
    data = Path(__file__).resolve().parent / "data"

    def robot(joint: str) -> str:
        return (f'[robot]\nname = "r"\n\n[[joints]]\nname = "j"\nbus = "can0"\nnode_id = 1\n'
                f"{joint}\n")

    return {
        "joint EDS with an unknown DataType": (robot('eds = "bad.eds"'), "j'.eds"),
        "joint EDS without the torque loop's objects": (
            robot(f'eds = "{data / "position_velocity_only.eds"}"'), "j'.eds"),
        "joint model K_j 1e-300": (robot('model = "tiny.toml"'), "torque_sensor_gain"),
        "joint on EtherCAT with an EDS that misses the ESI's objects": (
            robot('eds = "bad.eds"').replace('bus = "can0"\nnode_id = 1',
                                             'bus = "ethercat:eth1"\nslave = 0'), "j'.eds"),
        "negative weight": (robot("weights = { position = -1 }"), "weights.position"),
        "period 0": (robot("").replace('name = "r"', 'name = "r"\nperiod_us = 0'),
                     "period_us"),
        "reference beyond the limits": (
            robot('reference = { kind = "setpoint", position = 9.0 }'), "reference"),
    }


def run(capsys, command: str, argv: list[str]) -> tuple[int, str, str]:
    main = importlib.import_module(f"commands.{command}").main
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


def assert_refused(code: int, out: str, err: str, path: Path, needle: str) -> None:
    lines = err.strip().splitlines()
    assert code == 2, (code, out, err)
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "enabled" not in out and "ready" not in out, out
    assert str(path) in lines[0] and needle in lines[0], lines[0]


@pytest.mark.parametrize("case", sorted(malformed_eds()))
def test_a_malformed_eds_is_refused_in_one_line(capsys, tmp_path, case):
    text, needle = malformed_eds()[case]
    path = tmp_path / "drive.eds"
    path.write_text(text)
    for command, argv in (("actuatord", ["--sim", "--eds", str(path),
                                         "--no-multicast-scouting"]),
                          ("sim_bus", ["--bus", "virtual:malformed", "--eds", str(path)])):
        assert_refused(*run(capsys, command, argv), path, needle)


@pytest.mark.parametrize("case", sorted(malformed_esi()))
def test_a_malformed_esi_is_refused_before_the_interface_opens(capsys, tmp_path, case):
    text, needle = malformed_esi()[case]
    path = tmp_path / "drive.xml"
    path.write_text(text)
    for command in ("actuatord", "sim_bus"):
        code, out, err = run(capsys, command, [*NO_ETHERCAT, "--esi", str(path)])
        assert "interface" not in err, err  # refused before the interface was tried
        assert_refused(code, out, err, path, needle)


@pytest.mark.parametrize("case", sorted(malformed_models()))
def test_a_malformed_model_is_refused_before_the_drive_opens(capsys, tmp_path, case):
    text, needle = malformed_models()[case]
    path = tmp_path / "model.toml"
    path.write_text(text)
    assert_refused(*run(capsys, "actuatord", ["--sim", "--model", str(path),
                                              "--no-multicast-scouting"]), path, needle)


@pytest.mark.parametrize("case", sorted(malformed_robots()))
def test_a_malformed_robot_file_is_refused_when_loaded(capsys, tmp_path, case):
    robot_neighbours(tmp_path)
    text, needle = malformed_robots()[case]
    path = tmp_path / "robot.toml"
    path.write_text(text)
    for command in ("actuatord", "sim_bus"):
        assert_refused(*run(capsys, command, ["--sim", "--robot", str(path)]
                            if command == "actuatord" else ["--robot", str(path)]),
                       path, needle)


def test_a_bom_and_crlf_eds_and_robot_file_are_accepted(capsys, tmp_path):
    from protocol.dictionary import load_dictionary
    from robot.description import load_robot

    eds = tmp_path / "windows.eds"
    eds.write_bytes(b"\xef\xbb\xbf" + EDS.replace("\n", "\r\n").encode())
    shipped, windows = load_dictionary(eds_path()), load_dictionary(eds)
    assert windows[0x6041].data_type == shipped[0x6041].data_type
    assert windows[0x608F][1].default == 2 ** 19
    robot = tmp_path / "robot.toml"
    robot.write_bytes(b"\xef\xbb\xbf" + (f'[robot]\r\nname = "r"\r\n[[joints]]\r\nname = "j"\r\n'
                                          f'bus = "can0"\r\nnode_id = 1\r\neds = "{eds.name}"\r\n'
                                          ).encode())
    assert load_robot(robot).joints[0].eds == eds
    code, out, err = run(capsys, "actuatord", ["--sim", "--lockstep", "--duration", "0.05",
                                               "--eds", str(eds), "--no-multicast-scouting"])
    assert code == 0 and "enabled" in out, err


def test_a_parse_error_is_one_line_naming_the_file(tmp_path):
    from protocol.dictionary import load_dictionary

    path = Path(tmp_path) / "no_header.eds"
    path.write_text("ParameterName=x\n" + EDS)
    with pytest.raises(ValueError) as caught:
        load_dictionary(path)
    assert "\n" not in str(caught.value) and str(caught.value).startswith(str(path))


def test_a_virtual_drive_answers_its_hardware_encoder_where_the_eds_gives_no_default(
        capsys, tmp_path):
    from sim_bus.device import Cia402Device

    text = re.sub(r"(\[608Fsub1\][^\[]*?)DefaultValue=524288\n", r"\1", EDS)
    assert text != EDS
    path = tmp_path / "third_party.eds"
    path.write_text(text)
    device = Cia402Device(load_model(), Payload(), eds_path=path)
    assert device.read(objects.ENCODER_RESOLUTION, 1) == 2 ** 19  # not 0
    code, out, err = run(capsys, "actuatord", ["--sim", "--lockstep", "--duration", "0.05",
                                               "--eds", str(path), "--no-multicast-scouting"])
    assert code == 0 and "enabled" in out, err  # the master reads 2^19 and accepts it
