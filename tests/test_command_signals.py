"""A command's `main` called in a process of someone else's (a test, `tests/gap_case.py`)
gives back the SIGINT and SIGTERM handlers it set to end its run (`reports_failures`): left
in place, they set a stop event nobody waits for any more, and the caller ignored SIGTERM."""

import signal

from commands import bus_bench, recorder


def _handlers():
    return signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)


def test_bus_bench_gives_its_handlers_back(tmp_path):
    before = _handlers()
    # past the point where it sets them: the robot file is read inside the measurement
    assert bus_bench.main(["--robot", str(tmp_path / "missing.toml")]) == 2
    assert _handlers() == before


def test_a_recording_gives_its_handlers_back(tmp_path):
    before = _handlers()
    assert recorder.main(["--sinusoid", "--sim", "--lockstep", "--duration", "0.05",
                          "--no-progress", "-o", str(tmp_path / "r.mcap")]) == 0
    assert (tmp_path / "r.mcap").stat().st_size > 0
    assert _handlers() == before
