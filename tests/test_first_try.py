"""A fresh `sim-bus`, then a master on it, as a new user does: it works the first time, every
time (the drive's first SYNC used to wait 0.3-0.5 s for its physics to compile)."""

import subprocess
import sys

from driver.canopen_drive import CanOpenDrive
from model.parameters import load_model
from protocol.cia402 import State, state_from_statusword
from tests.conftest import udp_bus_spec

SIM_BUS = "commands.sim_bus"  # the module behind the sim-bus console script
LIMITS = load_model().limits
TRIES = 10


def test_a_fresh_sim_bus_is_driven_at_the_first_try_ten_times_out_of_ten():
    # ten fresh drives, each on its own bus, started together to spare the suite's time; each
    # gets its first SYNC from the master as soon as it says ready
    buses = [udp_bus_spec() for _ in range(TRIES)]
    procs = [subprocess.Popen([sys.executable, "-m", SIM_BUS, "--bus", bus],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for bus in buses]
    states = []
    try:
        for bus, proc in zip(buses, procs, strict=True):
            assert "ready" in proc.stdout.readline(), proc.stderr.read()
            # actuatord's real-time settings: a sample 100 ms late is a dead drive
            drive = CanOpenDrive.open(bus, 2, velocity_limit=LIMITS.velocity_max,
                                      response_timeout=0.1)
            try:
                drive.start()
                for _ in range(200):
                    sample = drive.sync()
                    drive.command_current(0.0)
                states.append(state_from_statusword(sample.statusword))
            finally:
                drive.close()
    finally:
        for proc in procs:
            proc.terminate()
            proc.wait(10)
    assert states == [State.OPERATION_ENABLED] * TRIES
