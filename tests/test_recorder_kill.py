"""A recorder process stopped by a real signal leaves a readable MCAP with its samples."""

import re
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from mcap.reader import make_reader

from protocol import telemetry
from recorder.reader import load_recording
from recorder.recording import RecordingError
from recorder.repair import repair_recording
from tests.conftest import wait_for

pytestmark = pytest.mark.subprocess  # runs the commands as processes


def start(path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "commands.recorder", "--exciting-trajectory",
                             "--sim", "--lockstep", "--no-progress", "-o", str(path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    # 120 kB: about 1200 samples (State + Command)
    wait_for(lambda: path.exists() and path.stat().st_size >= 120_000, 60, 0.05)
    assert proc.poll() is None, proc.stderr.read()
    return proc


def contiguous(recording) -> None:
    assert recording.t[0] == pytest.approx(1e-3)
    np.testing.assert_allclose(np.diff(recording.t), 1e-3, atol=1e-9)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_interrupted_recording_keeps_every_sample(tmp_path, signum):
    path = tmp_path / "run.mcap"
    proc = start(path)
    proc.send_signal(signum)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 1
    samples = int(re.search(r"interrupted after (\d+) samples", err).group(1))
    recording = load_recording(path)
    assert len(recording) == samples > 1000
    contiguous(recording)


def test_killed_recording_is_readable_up_to_the_last_flushed_chunk(tmp_path):
    path = tmp_path / "run.mcap"
    proc = start(path)
    proc.kill()
    proc.wait(30)
    recording = load_recording(path)  # no summary, but every complete chunk reads
    assert len(recording) > 1000
    contiguous(recording)


def test_twenty_kills_at_random_moments_leave_twenty_readable_files(tmp_path):
    """SIGKILL at random moments of short recordings: every file reads, holds contiguous
    samples from the start, and loses at most the open chunk (about 0.12 s at 1 kHz)."""
    import random
    from concurrent.futures import ThreadPoolExecutor

    def one(seed: int) -> tuple[int, float]:
        rng = random.Random(seed)
        path = tmp_path / f"kill{seed}.mcap"
        proc = subprocess.Popen([sys.executable, "-m", "commands.recorder", "--sinusoid",
                                 # far longer than the kill comes: 30 s of drive time took
                                 # under 1.5 s in lock-step once the cycle got faster
                                 "--duration", "600", "--sim", "--lockstep", "--no-progress",
                                 "--seed", str(seed), "-o", str(path)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        # 2 kB: past the header, metadata and provisional end (about 460 bytes), so the first
        # chunk is in the file. A recorder that fails before that leaves no file at all.
        wait_for(lambda: proc.poll() is not None or (
            path.exists() and path.stat().st_size >= 2_000), 60, 0.01)
        time.sleep(rng.uniform(0.0, 1.5))
        proc.kill()
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == -signal.SIGKILL, f"{path.name}: the recorder ended by " \
            f"itself before the kill: {err.strip()}"
        try:
            recording = load_recording(path)
        except RecordingError as exc:
            # the kernel may stop a write between pages when SIGKILL arrives: a kill inside a
            # chunk's write leaves it cut short, which the reader refuses naming the cut and
            # the repair (every complete chunk kept) makes whole
            assert "truncated MCAP" in str(exc) and "recorder repair" in str(exc), exc
            repaired = path.with_name(f"repaired{seed}.mcap")
            repair_recording(path, repaired)
            path = repaired
            recording = load_recording(path)
        contiguous(recording)
        with open(path, "rb") as fh:  # the standard reader finds the same samples
            assert len(recording) == sum(1 for _ in make_reader(fh).iter_messages(
                [telemetry.key_expr(telemetry.DEFAULT_PREFIX, "state")]))
        return len(recording), recording.t[-1]

    with ThreadPoolExecutor(2) as pool:
        results = list(pool.map(one, range(20)))
    assert len(results) == 20
    assert all(samples > 0 for samples, _ in results)
    assert len({samples for samples, _ in results}) > 5  # the moments really differ
