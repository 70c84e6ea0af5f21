"""A fresh `sim-bus`, then `actuatord` on it, as a new user does: it works the first time,
every time (the drive's first SYNC used to wait 0.3-0.5 s for its physics to compile)."""

import subprocess
import sys

import pytest

from tests.conftest import udp_bus_spec

pytestmark = pytest.mark.subprocess  # runs the commands as processes

TRIES = 10


@pytest.mark.real_time
def test_a_fresh_sim_bus_is_driven_by_actuatord_at_the_first_try_ten_times_out_of_ten():
    # ten fresh drives, each on its own bus, started together to spare the suite's time; once
    # every one says ready, each gets actuatord (real time: a sample 100 ms late is a dead
    # drive) in turn. Not while others still start, nor two at a time: a drive process that
    # shares its core with starting ones (and, on a busy host, with other work) answers late,
    # which is the host's overload, not the first-try delay this test is about
    buses = [udp_bus_spec() for _ in range(TRIES)]
    procs = [subprocess.Popen([sys.executable, "-m", "commands.sim_bus", "--bus", bus],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for bus in buses]
    try:
        for proc in procs:
            ready = proc.stdout.readline()
            assert "ready" in ready, proc.stderr.read()
        results = []
        for bus in buses:
            run = subprocess.run([sys.executable, "-m", "commands.actuatord", "--bus", bus,
                                  "--duration", "0.2", "--no-multicast-scouting"],
                                 capture_output=True, text=True, timeout=120)
            results.append((run.returncode, run.stderr.strip()))
    finally:
        for proc in procs:
            proc.terminate()
            proc.wait(10)
    # warnings (a late cycle on a busy host) may be printed; what counts is that each ran
    assert [code for code, _ in results] == [0] * TRIES, results
