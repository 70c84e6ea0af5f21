"""The bus is chosen as python-can users expect (-i/-c/-b, its environment and config files,
every interface it ships) and `--can-log` writes what crossed it with python-can's own writers,
readable by `can.LogReader`."""

import os
import subprocess
import sys

import can
import pytest

from commands import actuatord, sim_bus
from commands.bus_options import bus_config, check_drive_arguments, open_drive
from driver.clock import WallClock
from model.parameters import Payload, load_model
from protocol import pdo
from sim_bus.canopen_node import CanOpenNode
from sim_bus.device import Cia402Device
from tests.conftest import sim_bus_process, udp_port

pytestmark = pytest.mark.subprocess  # runs the commands as processes

NODE = 2
SYNC = 0x80
TPDOS = [layout.cob_id(NODE) for layout in pdo.DEFAULT_TPDOS]
RPDO = pdo.RPDO_COMMAND.cob_id(NODE)
TPDO1 = pdo.DEFAULT_TPDOS[0]


@pytest.fixture
def no_can_config(monkeypatch, tmp_path):
    """No python-can configuration from this machine: an empty home, no CAN_* variables."""
    monkeypatch.setenv("HOME", str(tmp_path))
    for name in list(os.environ):
        if name.startswith("CAN_"):
            monkeypatch.delenv(name)
    return tmp_path


def parse(*argv: str):
    return actuatord.build_parser().parse_args(list(argv))


def test_python_can_options_name_the_bus(no_can_config):
    config = bus_config(parse("-i", "pcan", "-c", "PCAN_USBBUS1", "-b", "500000"))
    assert (config["interface"], config["channel"], config["bitrate"]) == (
        "pcan", "PCAN_USBBUS1", 500000)
    config = bus_config(parse("-i", "udp_multicast", "-c", "239.0.0.9", "--bus-kwargs",
                              "port=45000"))
    assert (config["interface"], config["channel"], config["port"]) == (
        "udp_multicast", "239.0.0.9", 45000)
    for spec, interface in (("kvaser:0", "kvaser"), ("slcan:/dev/ttyACM0", "slcan"),
                            ("pcan:PCAN_USBBUS1", "pcan"), ("vcan0", "socketcan")):
        assert bus_config(parse("--bus", spec))["interface"] == interface
    assert bus_config(parse("--bus", "vcan1", "-b", "1000000"))["bitrate"] == 1000000
    # nothing given and nothing configured: the documented default
    assert (bus_config(parse())["interface"], bus_config(parse())["channel"]) == (
        "socketcan", "vcan0")
    with pytest.raises(ValueError, match="both name the bus"):
        bus_config(parse("--bus", "vcan0", "-c", "can1"))
    with pytest.raises(ValueError, match="needs no bus"):
        check_drive_arguments(parse("--sim", "-c", "can1"))


def test_environment_and_canrc_are_python_cans_own(no_can_config, monkeypatch):
    (no_can_config / ".canrc").write_text("[default]\ninterface = virtual\nchannel = rc\n"
                                          "bitrate = 250000\n")
    config = bus_config(parse())
    assert (config["interface"], config["channel"], config["bitrate"]) == (
        "virtual", "rc", 250000)
    monkeypatch.setenv("CAN_INTERFACE", "udp_multicast")
    monkeypatch.setenv("CAN_CHANNEL", "239.0.0.8")
    config = bus_config(parse())
    assert (config["interface"], config["channel"]) == ("udp_multicast", "239.0.0.8")
    assert bus_config(parse("-c", "239.0.0.7"))["channel"] == "239.0.0.7"  # options win


@pytest.mark.real_time
def test_can_log_over_a_python_can_bus_holds_every_frame(no_can_config, tmp_path):
    """In one process on python-can's virtual bus, in lock-step: every SYNC the master sent,
    every TPDO that answered it and every RPDO, in a candump .log that can.LogReader reads."""
    channel = f"log-{os.getpid()}"
    path = tmp_path / "bus.log"
    args = parse("--bus", f"virtual:{channel}", "--can-log", str(path))
    check_drive_arguments(args)
    sim_network = can.Bus(interface="virtual", channel=channel)
    import canopen

    network = canopen.Network(sim_network)
    network.connect()
    sim = CanOpenNode(network, NODE, Cia402Device(load_model(), Payload(), node_id=NODE),
                      clock=WallClock())
    sim.boot()
    connection = open_drive(args, load_model(), load_model(), Payload(), response_timeout=5.0)
    try:
        group = connection.group
        group.start()
        for _ in range(50):
            group.sync()
            group.command_currents([0.0])
    finally:
        connection.close()
        sim.close()
        network.disconnect()
    frames = list(can.LogReader(path))
    check_cycles(frames, expected=50)
    assert any(f.arbitration_id == 0x702 for f in frames)  # the drive's heartbeat, received


def check_cycles(frames: list[can.Message], expected: int | None = None) -> int:
    """Every SYNC in the log, numbered 1..240 in turn, is answered by the three TPDOs (TPDO1
    echoing its counter) and followed by one RPDO; returns the number of cycles."""
    syncs = [f for f in frames if f.arbitration_id == SYNC]
    counters = [f.data[0] for f in syncs]
    assert counters == [(k % 240) + 1 for k in range(len(counters))]
    echoed = [pdo.decode(TPDO1, f.data)[pdo.SYNC_ECHO.index] for f in frames
              if f.arbitration_id == TPDOS[0]]
    assert echoed == counters
    for cob_id in TPDOS[1:]:
        assert sum(f.arbitration_id == cob_id for f in frames) == len(syncs), hex(cob_id)
    assert sum(f.arbitration_id == RPDO for f in frames) >= len(syncs)
    if expected is not None:
        assert len(syncs) == expected
    return len(syncs)


def cycles_in(summary: str) -> int:
    line = next(line for line in summary.splitlines() if " cycles, " in line)
    return int(line.split(": ", 1)[1].split(" cycles")[0])


def test_can_log_of_the_sim_link_in_lockstep(tmp_path):
    """--sim hands frames between two networks without python-can; the log taps that link,
    so the run's every SYNC and PDO is in the file all the same (.asc here)."""
    path = tmp_path / "sim.asc"
    proc = subprocess.run([sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep",
                           "--duration", "0.3", "--no-multicast-scouting", "--can-log",
                           str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    check_cycles(list(can.LogReader(path)), expected=cycles_in(proc.stdout))


@pytest.mark.real_time
def test_sim_bus_and_actuatord_on_udp_multicast_with_python_can_options(tmp_path):
    """Two processes, the bus named the python-can way; both logs (candump .log and .blf)
    read back with can.LogReader and hold every SYNC and PDO of the run."""
    import random

    group, port = f"239.0.1.{random.randint(1, 250)}", str(udp_port())
    bus = ["-i", "udp_multicast", "-c", group, "--bus-kwargs", f"port={port}"]
    master_log, drive_log = tmp_path / "master.log", tmp_path / "drive.blf"
    with sim_bus_process(None, *bus, "--can-log", str(drive_log)):
        proc = subprocess.run([sys.executable, "-m", "commands.actuatord", *bus, "--duration",
                               "1", "--no-multicast-scouting", "--can-log", str(master_log)],
                              capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert f"on udp_multicast:{group} enabled" in proc.stdout
    cycles = check_cycles(list(can.LogReader(master_log)), expected=cycles_in(proc.stdout))
    drive_frames = [f for f in can.LogReader(drive_log) if f.arbitration_id in (SYNC, RPDO,
                                                                                 *TPDOS)]
    assert check_cycles(drive_frames) == cycles


def test_log_level_is_on_every_command():
    for module in ("actuatord", "sim_bus", "recorder", "identify", "model_gap", "bench",
                   "bus_bench"):
        proc = subprocess.run([sys.executable, "-m", f"commands.{module}", "--help"],
                              capture_output=True, text=True, timeout=60)
        assert "--log-level" in proc.stdout, module
    proc = subprocess.run([sys.executable, "-m", "commands.dashboard", "tui", "--help"],
                          capture_output=True, text=True, timeout=60)
    assert "--log-level" in proc.stdout
    assert sim_bus.build_parser().parse_args(["--log-level", "debug"]).log_level == "debug"


def test_a_fault_logged_by_a_library_and_reported_by_the_command_shows_once():
    code = ("import logging\n"
            "from commands.log_options import configure_logging, job_error\n"
            "configure_logging('recorder', 'warning')\n"
            "logging.getLogger('driver.canopen_drive').error('%s', 'node 2: heartbeat lost')\n"
            "logging.getLogger('driver.canopen_drive').info('not shown at warning')\n"
            "raise SystemExit(job_error('recorder', 'node 2: heartbeat lost'))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 1
    assert proc.stderr == "recorder: error: node 2: heartbeat lost\n"


@pytest.mark.real_time
def test_a_lost_drive_is_reported_once_end_to_end(tmp_path):
    """sim-bus stops its heartbeat; the master's watchdog logs it, the recorder fails with it:
    the reason is read once."""
    import random

    bus = f"udp_multicast:239.0.2.{random.randint(1, 250)}:{udp_port()}"
    with sim_bus_process(bus, "--inject-fault", "heartbeat_stops@0.5"):
        proc = subprocess.run([sys.executable, "-m", "commands.recorder", "--sinusoid",
                               "--duration", "5", "--bus", bus, "--no-progress", "-o",
                               str(tmp_path / "r.mcap")],
                              capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("heartbeat missing") == 1, proc.stderr
