"""The loop's safety net end to end on the virtual drive: faults are published, the commanded
current never leaves the limit, a failing drive stops the loop."""

import gc
import subprocess
import sys

import numpy as np
import pytest

from controller.loop import ControlLoop, LoopOptions
from controller.messages import topic_of
from controller.mpc import Mpc
from controller.problem import OcpSettings
from driver.clock import DriveClock, collector_off_the_cycle
from driver.drive_group import single_joint
from model.parameters import load_model
from tests.conftest import virtual_pair

MODEL = load_model()


def collect():
    messages = []
    return messages, lambda message: messages.append((topic_of(message), message))


def test_failing_solver_holds_position_and_says_so_every_cycle():
    messages, publish = collect()
    mpc = Mpc(MODEL, OcpSettings().with_weights(position=1e308))  # compiled code loaded first
    with virtual_pair() as (sim, drive):
        drive.start()
        loop = ControlLoop(single_joint(drive), mpc, LoopOptions(clock=DriveClock(), duration=0.5),
                           [publish])
        report = loop.run()
        final_position = sim.device.plant.position
    assert report.exit_code == 0 and report.fallbacks == report.cycles == 500
    faults = [f for topic, f in messages if topic == "fault"]
    assert len(faults) == 500
    assert faults[0].source == "controller" and "solver" in faults[0].cause
    commands = [f for topic, f in messages if topic == "command"]
    assert all(c.fallback and abs(c.current) <= 6.0 for c in commands)
    assert abs(final_position - commands[0].reference_position) > 0.1  # did not track...
    assert abs(final_position - (-0.0997)) < 0.01  # ... it held where it was


def test_drive_fault_stops_the_loop_with_exit_code_1_and_a_fault_message():
    messages, publish = collect()
    mpc = Mpc(MODEL)
    with virtual_pair() as (sim, drive):
        drive.start()
        drive.node.sdo[0x2003].raw = 100  # trip at 0.1 A: the first real command faults it
        loop = ControlLoop(single_joint(drive), mpc, LoopOptions(clock=DriveClock(), duration=2.0),
                           [publish])
        report = loop.run()
    assert report.exit_code == 1
    assert "drive" in report.reason
    faults = [f for topic, f in messages if topic == "fault"]
    assert faults[-1].source == "drive"
    assert report.cycles < 10


def test_plot_option_writes_the_figures(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep", "--duration", "0.5",
         "--no-multicast-scouting", "--plot", str(tmp_path)],
        capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    for name in ("position.png", "current.png"):
        data = (tmp_path / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_commands_print_help():
    for module in ("commands.sim_bus", "commands.actuatord", "commands.bench", "commands.bus_bench",
                   "commands.recorder", "commands.identify", "commands.model_gap",
                   "commands.dashboard"):
        proc = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True,
                              text=True, timeout=60)
        assert proc.returncode == 0 and "usage:" in proc.stdout, module


def test_model_commands_answer_help_without_the_numerical_code():
    """`identify --help` and `model-gap --help` took ~2 s importing scipy and numba before
    parsing (issue 26); they import them once the arguments are parsed."""
    script = ("import io, sys\n"
              "from contextlib import redirect_stdout, suppress\n"
              "from commands import identify, model_gap\n"
              "for command in (identify, model_gap):\n"
              "    with suppress(SystemExit), redirect_stdout(io.StringIO()):\n"
              "        command.main(['--help'])\n"
              "print(sorted(m for m in ('scipy', 'numba') if m in sys.modules))\n")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]", proc.stdout


def test_ring_stats_percentiles():
    from controller.loop import RingStats

    stats = RingStats(window=100)
    for value in range(1000):
        stats.add(float(value))
    assert stats.count == 1000 and stats.max == 999.0
    assert stats.percentile(50) == np.percentile(np.arange(900, 1000), 50)


def test_a_loop_runs_with_the_start_up_heap_frozen_and_gives_it_back():
    """What exists when a loop starts is out of the collector's full passes while it runs
    (gc.freeze), and back in them afterwards, also when the loop raises: a test session runs
    many loops in one process."""
    before = gc.get_freeze_count()
    with collector_off_the_cycle():
        assert gc.get_freeze_count() > before
    assert gc.get_freeze_count() == 0
    with pytest.raises(RuntimeError), collector_off_the_cycle():
        raise RuntimeError("the loop failed")
    assert gc.get_freeze_count() == 0
