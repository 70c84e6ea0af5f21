import itertools
import os
import random
import socket
import subprocess
import sys
import time
from contextlib import contextmanager

import pytest

from driver.canopen_drive import CanOpenDrive, open_network
from model.parameters import Payload, load_model
from sim_bus.canopen_node import CanOpenNode
from sim_bus.device import Cia402Device
from sim_bus.plant import SensorNoise

_channels = itertools.count()


@contextmanager
def virtual_pair(payload: Payload = Payload(), noise: SensorNoise = SensorNoise(), model=None,
                 **drive_kwargs):
    """A virtual drive (its CANopen node; the device is `sim.device`) and our master on a
    private python-can `virtual` channel."""
    channel = f"virtual:test-{os.getpid()}-{next(_channels)}"
    sim_network = open_network(channel)
    device = Cia402Device(model or load_model(), payload, noise, node_id=2)
    sim = CanOpenNode(sim_network, 2, device)
    sim.boot()
    master = CanOpenDrive(open_network(channel), 2, **drive_kwargs)
    try:
        yield sim, master
    finally:
        master.close()
        sim.close()
        sim_network.disconnect()


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
def sim_bus_process(bus: str, *extra: str):
    proc = subprocess.Popen([sys.executable, "-m", "sim_bus.cli", "--bus", bus, *extra],
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
