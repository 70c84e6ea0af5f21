"""Special, huge and clashing files on every file option (issue 28 items 7 and 8): each is
refused in one line, exit code 2, within a second, before anything is read or written. The
commands run in this process (their `main`), so the whole matrix costs seconds: a device, a
FIFO or a huge file must never be opened at all, which a hang or a MemoryError would show."""

import importlib
import os
import time
from pathlib import Path

import pytest

from model.parameters import default_model_path
from protocol import eds_path, esi_path

CSV = "# payload_mass=0\nt,q,current,joint_torque\n0.000,-1.0,0.1,0.2\n0.001,-1.0,0.1,0.2\n"
HUGE = 100 * 1024 * 1024  # bytes: the size of the garbage TOML
NO_ZENOH = ["--no-multicast-scouting"]


def run(capsys, command: str, argv: list[str]) -> tuple[int, str, str, float]:
    """A command's main in this process: (exit code, stdout, stderr, seconds)."""
    main = importlib.import_module(f"commands.{command}").main
    started = time.perf_counter()
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse refuses by exiting
        code = exc.code
    elapsed = time.perf_counter() - started
    out, err = capsys.readouterr()
    return code, out, err, elapsed


def refused(code: int, out: str, err: str) -> list[str]:
    """The checks every refusal must pass; the one line is returned for its wording."""
    lines = err.strip().splitlines()
    assert code == 2, (code, out, err)
    assert len(lines) == 1 and "Traceback" not in err, err
    assert "enabled" not in out and "ready" not in out, out  # nothing was started
    return lines


@pytest.fixture
def hostile(tmp_path):
    """/dev/zero, /dev/urandom, a FIFO, a sparse 100 MB file (read, it would take seconds
    and its size in memory) and a path too long to look up."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    huge = tmp_path / "huge.bin"
    with open(huge, "wb") as fh:
        fh.truncate(HUGE)
    return {"zero": "/dev/zero", "urandom": "/dev/urandom", "fifo": str(fifo),
            "huge": str(huge), "long": str(tmp_path / ("x" * 5000))}  # ENAMETOOLONG


def _file_options(tmp: Path) -> list[tuple[str, str, list[str]]]:
    """(command, option, argv with {} where the file goes): every option that reads a file,
    with the other options set so that the file is the only thing wrong."""
    rec = tmp / "rec.csv"  # written by the test that runs the case
    out = str(tmp / "out.mcap")
    ethercat = ["--bus", "ethercat:nonexistent0"]
    return [
        ("actuatord", "--model", ["--sim", "--model", "{}", *NO_ZENOH]),
        ("actuatord", "--robot", ["--sim", "--robot", "{}", *NO_ZENOH]),
        ("actuatord", "--eds", ["--sim", "--eds", "{}", *NO_ZENOH]),
        ("actuatord", "--esi", [*ethercat, "--esi", "{}", *NO_ZENOH]),
        ("actuatord", "--zenoh-config", ["--sim", "--zenoh-config", "{}", "--duration", "0.01"]),
        ("sim_bus", "--model", ["--bus", "virtual:hostile", "--model", "{}"]),
        ("sim_bus", "--robot", ["--robot", "{}"]),
        ("sim_bus", "--eds", ["--bus", "virtual:hostile", "--eds", "{}"]),
        ("sim_bus", "--esi", [*ethercat, "--esi", "{}"]),
        ("recorder", "--model", ["--exciting-trajectory", "--sim", "--model", "{}", "-o", out]),
        ("recorder", "--robot", ["--exciting-trajectory", "--sim", "--robot", "{}", "--joint",
                                 "j", "-o", out]),
        ("recorder", "--eds", ["--exciting-trajectory", "--sim", "--eds", "{}", "-o", out]),
        ("recorder", "--esi", ["--exciting-trajectory", *ethercat, "--esi", "{}", "-o", out]),
        ("recorder", "--zenoh-config", ["--zenoh", "x/**", "--zenoh-config", "{}", "-o", out,
                                        "--duration", "0.01"]),
        ("recorder", "export FILE", ["export", "{}", "-o", str(tmp / "out.csv")]),
        ("recorder", "repair FILE", ["repair", "{}", "-o", out]),
        ("identify", "NOLOAD", ["{}", str(rec), "--payload-mass", "1", "--payload-position",
                                "0,0.05", "-o", str(tmp / "m.toml")]),
        ("identify", "LOAD", [str(rec), "{}", "--payload-mass", "1", "--payload-position",
                              "0,0.05", "-o", str(tmp / "m.toml")]),
        ("identify", "--model", [str(rec), str(rec), "--model", "{}", "-o", str(tmp / "m.toml")]),
        ("model_gap", "RECORDING", ["{}", "--model", str(default_model_path())]),
        ("model_gap", "--model", [str(rec), "--model", "{}"]),
        ("dashboard", "--zenoh-config", ["set", "weights", "position=300", "--zenoh-config",
                                         "{}"]),
    ]


OPTIONS = [(command, option) for command, option, _ in _file_options(Path("/nonexistent"))]


@pytest.mark.timeout(60)
@pytest.mark.parametrize("command,option", OPTIONS)
def test_special_and_huge_files_are_refused_at_once_on_every_file_option(
        capsys, tmp_path, hostile, command, option):
    argv = next(a for c, o, a in _file_options(tmp_path) if (c, o) == (command, option))
    (tmp_path / "rec.csv").write_text(CSV)
    for kind, path in hostile.items():
        code, out, err, elapsed = run(capsys, command, [path if a == "{}" else a
                                                        for a in argv])
        (line,) = refused(code, out, err)
        assert path[:100] in line, line  # the file is named
        assert elapsed < 1.0, f"{command} {option} {kind}: {elapsed:.2f} s"
    assert not (tmp_path / "out.mcap").exists()


def test_the_check_reads_nothing_and_names_what_was_expected(tmp_path):
    from protocol.input_files import InputFileError, check_input_file, read_input_text

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    for path, needle in (("/dev/zero", "is a character device"), (fifo, "is a FIFO"),
                         (tmp_path, "is a directory"), (tmp_path / "no", "no such file"),
                         ("x" * 5000, "cannot read")):
        with pytest.raises(InputFileError, match=needle) as caught:
            check_input_file(path, "a model TOML", 1024)
        assert "expected a model TOML" in str(caught.value)
        assert "\n" not in str(caught.value)
    big = tmp_path / "big.toml"
    big.write_bytes(b"a" * 2048)
    with pytest.raises(InputFileError, match="2048 bytes; expected a model TOML of at most"):
        check_input_file(big, "a model TOML", 1024)
    crlf = tmp_path / "crlf.txt"
    crlf.write_bytes(b"\xef\xbb\xbfa\r\nb\rc\n")
    assert read_input_text(crlf, "text", 1024) == "a\nb\nc\n"


def test_a_csv_field_over_the_csv_modules_limit_is_one_line(capsys, tmp_path):
    rec = tmp_path / "rec.csv"
    rec.write_text("t,q,current,joint_torque\n" + "1" * 200_000 + ",1,1,1\n")
    code, out, err, _ = run(capsys, "model_gap", [str(rec), "--model",
                                                  str(default_model_path())])
    (line,) = refused(code, out, err)
    assert str(rec) in line and "field larger than field limit" in line


# --- item 7: an output that is an input, or not a regular file --------------------------------

def _recording(tmp: Path) -> Path:
    from tests.test_recording_files import synthetic

    path = tmp / "a.mcap"
    synthetic(path, cycles=50)
    return path


def _clashes(tmp: Path) -> list[tuple[str, list[str]]]:
    """(command, argv) whose output is one of its inputs, or another output."""
    mcap = _recording(tmp)
    csv = tmp / "b.csv"
    csv.write_text(CSV)
    model = tmp / "m.toml"
    model.write_text(default_model_path().read_text())
    link = tmp / "link.mcap"
    link.symlink_to(mcap)
    hard = tmp / "hard.csv"
    os.link(csv, hard)
    return [
        ("recorder", ["export", str(mcap), "-o", str(mcap)]),
        ("recorder", ["export", str(mcap), "-o", str(link)]),
        ("recorder", ["repair", str(link), "-o", str(mcap)]),
        ("identify", [str(csv), str(hard), "-o", str(hard), "--payload-mass", "1",
                      "--payload-position", "0,0.05"]),
        ("identify", [str(csv), str(csv), "-o", str(model), "--model", str(model)]),
        ("model_gap", [str(csv), "--model", str(model), "--report", str(csv)]),
        ("model_gap", [str(csv), "--model", str(model), "-o", str(model)]),
        ("model_gap", [str(csv), "--model", str(model), "-o", str(tmp / "x.toml"),
                       "--report", str(tmp / "x.toml")]),
        ("recorder", ["--exciting-trajectory", "--sim", "--model", str(model), "-o",
                      str(model)]),
        ("recorder", ["--exciting-trajectory", "--sim", "-o", str(tmp / "r.mcap"),
                      "--can-log", str(tmp / "r.mcap")]),
    ]


def test_an_output_that_is_an_input_is_refused_before_anything_is_written(capsys, tmp_path):
    for command, argv in _clashes(tmp_path):
        before = {p: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
        code, out, err, _ = run(capsys, command, argv)
        (line,) = refused(code, out, err)
        assert "the same file as" in line or "is the file being repaired" in line, line
        after = {p: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
        assert after == before, f"{command} {argv}: files changed"


def test_a_device_or_fifo_as_an_output_is_refused_and_left_alone(capsys, tmp_path):
    mcap = _recording(tmp_path)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    code, out, err, _ = run(capsys, "recorder", ["export", str(mcap), "-o",
                                                 str(tmp_path / ("x" * 5000))])
    assert "cannot use this path (File name too long)" in refused(code, out, err)[0]
    for output in ("/dev/full", "/dev/null", str(fifo)):
        for argv in (["repair", str(mcap), "-o", output], ["export", str(mcap), "-o", output]):
            code, out, err, elapsed = run(capsys, "recorder", argv)
            (line,) = refused(code, out, err)
            assert "is not a regular file" in line and elapsed < 1.0, line
    assert Path("/dev/full").is_char_device() and Path("/dev/null").is_char_device()
    assert fifo.is_fifo()


def test_shipped_files_still_pass_the_checks():
    from protocol.dictionary import load_dictionary
    from protocol.esi import load_esi

    load_dictionary(eds_path())
    load_esi(esi_path())
