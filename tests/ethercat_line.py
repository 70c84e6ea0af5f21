"""Test rig for EtherCAT without hardware: a network namespace of the test's own with a veth
pair in it, virtual slaves in a separate process on one end (`ethercat_slave_process.py`,
killable like a real line), and the master in this process's thread, entered into the
namespace with setns(2). The machine's own interfaces are never touched; the namespace goes
away afterwards. Skips (with the reason) where the kernel lacks namespaces or raw sockets."""

import contextlib
import ctypes
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MASTER_PORT, LINE_PORT = "ecm0", "ecs0"
CLONE_NEWNET = 0x40000000
_setns_lock = threading.Lock()


@dataclass(frozen=True)
class Namespace:
    name: str
    master: str = MASTER_PORT  # the interface the master opens
    line: str = LINE_PORT  # the interface the slaves answer on


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)


@contextlib.contextmanager
def network_namespace():
    if shutil.which("ip") is None:
        pytest.skip("no `ip` command (iproute2) to make a network namespace")
    name = f"ecat-{secrets.token_hex(4)}"
    made = _ip("netns", "add", name)
    if made.returncode:
        pytest.skip(f"cannot make a network namespace: {made.stderr.strip()}")
    try:
        veth = _ip("-n", name, "link", "add", MASTER_PORT, "type", "veth", "peer", "name",
                   LINE_PORT)
        if veth.returncode:
            pytest.skip(f"cannot make a veth pair: {veth.stderr.strip()}")
        for port in (MASTER_PORT, LINE_PORT):
            _ip("-n", name, "link", "set", port, "up")
        namespace = Namespace(name)
        with entered(namespace):
            try:
                import socket
                socket.socket(socket.AF_PACKET, socket.SOCK_RAW).close()
            except OSError as exc:
                pytest.skip(f"no raw packet sockets here: {exc}")
        yield namespace
    finally:
        _ip("netns", "del", name)


@contextlib.contextmanager
def entered(namespace: Namespace):
    """Run the block with this thread in the namespace (sockets made in it stay there)."""
    libc = ctypes.CDLL(None, use_errno=True)
    with _setns_lock, open("/proc/thread-self/ns/net") as home, \
            open(f"/run/netns/{namespace.name}") as target:
        if libc.setns(target.fileno(), CLONE_NEWNET):
            pytest.skip(f"setns: {os.strerror(ctypes.get_errno())}")
        try:
            yield
        finally:
            if libc.setns(home.fileno(), CLONE_NEWNET):
                raise OSError(ctypes.get_errno(), "setns back to the test's namespace")


class SlaveLine:
    """Virtual slaves in their own process on the namespace's line port."""

    def __init__(self, namespace: Namespace, slaves: int = 1, *extra: str):
        script = Path(__file__).with_name("ethercat_slave_process.py")
        self.process = subprocess.Popen(
            ["ip", "netns", "exec", namespace.name, sys.executable, str(script),
             namespace.line, str(slaves), *extra],
            cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, text=True,
            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        line = self.process.stdout.readline()
        if line.strip() != "ready":
            self.process.kill()
            raise RuntimeError(f"slave process did not start: {line!r} "
                               f"{self.process.stderr.read()}")

    def kill(self) -> None:
        """Power off: SIGKILL, nothing answers any more."""
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(10)

    def report(self) -> list[dict]:
        """Stop the slaves (SIGTERM) and return what each one ended as."""
        self.process.send_signal(signal.SIGTERM)
        out, err = self.process.communicate(timeout=20)
        lines = [line for line in out.splitlines() if line.startswith("[")]
        if not lines:
            raise RuntimeError(f"no report from the slave process: {out!r} {err!r}")
        return json.loads(lines[-1])

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(10)
        for stream in (self.process.stdout, self.process.stderr):
            stream.close()


@contextlib.contextmanager
def slave_line(namespace: Namespace, slaves: int = 1, *extra: str):
    line = SlaveLine(namespace, slaves, *extra)
    try:
        yield line
    finally:
        line.close()
