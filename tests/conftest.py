import random
import socket
import subprocess
import sys
import time
from contextlib import contextmanager

import pytest

from driver.canopen_drive import CanOpenDrive
from model.parameters import Payload, load_model
from sim_bus.embedded import EmbeddedDrive
from sim_bus.plant import SensorNoise


@contextmanager
def virtual_pair(payload: Payload = Payload(), noise: SensorNoise = SensorNoise(), model=None,
                 lockstep: bool = True, **drive_kwargs):
    """A virtual drive (its CANopen node; the device is `sim.device`) and our master, linked
    as `--sim` links them: each frame is delivered in its sender's thread, so a SYNC comes back
    with its TPDOs before `send` returns and no thread scheduling can delay an answer. Lock-step
    by default: both sides' watchdogs count cycles, so a busy host cannot trip them."""
    model = model or load_model()
    embedded = EmbeddedDrive(model, payload, noise, 2, lockstep=lockstep)
    master = CanOpenDrive(embedded.master_network, 2, velocity_limit=model.limits.velocity_max,
                          drive_gain=model.parameters.drive_gain, lockstep=lockstep,
                          **drive_kwargs)
    try:
        yield embedded.node, master
    finally:
        master.close()
        embedded.close()


@pytest.fixture
def pair():
    with virtual_pair() as p:
        yield p


def free_port() -> int:
    """A TCP port nobody listens on right now (the kernel's pick), for Zenoh and WebSocket."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def udp_bus_spec() -> str:
    """A multicast group and port of our own, so parallel runs do not hear each other."""
    return f"udp_multicast:239.0.0.{random.randint(1, 250)}:{random.randint(20000, 60000)}"


@contextmanager
def sim_bus_process(bus: str | None, *extra: str):
    """sim-bus in its own process on `bus` (a --bus spec; None: the bus options in `extra`)."""
    where = ["--bus", bus] if bus is not None else []
    proc = subprocess.Popen([sys.executable, "-m", "commands.sim_bus", *where, *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert "ready" in line, f"sim-bus did not start: {line!r} {proc.stderr.read()}"
        time.sleep(0.05)
        yield proc
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
