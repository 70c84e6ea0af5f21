"""A private virtual cable for a virtual EtherCAT line: a network namespace of its own with a
veth pair in it, the slaves in a separate process on one end, the master on the other.

The machine's own interfaces are never touched and the namespace is deleted on close. The
master runs in the caller's thread, moved into the namespace with setns(2) for the time of a
`with line.entered():` block (sockets made there stay in the namespace). The slaves run in a
spawned process that can be killed like a real line loses power. Needs root (or
CAP_SYS_ADMIN and CAP_NET_RAW); `LinkUnavailable` says what is missing.
"""

import contextlib
import ctypes
import gc
import multiprocessing
import os
import secrets
import shutil
import signal
import subprocess
import threading
from collections.abc import Iterator

from model.parameters import ActuatorModel, Payload
from sim_bus.device import Cia402Device
from sim_bus.plant import SensorNoise

MASTER_PORT, LINE_PORT = "ecm0", "ecs0"
CLONE_NEWNET = 0x40000000
START_TIMEOUT = 60.0  # s for the slave process to import, build its drives and open the port
_setns_lock = threading.Lock()


class LinkUnavailable(RuntimeError):
    """This kernel or these privileges cannot make the virtual cable (the reason is the
    message): no `ip`, no network namespaces, no veth, no raw packet sockets."""


class VirtualLink:
    """Namespace `ecat-<random>` with the veth pair MASTER_PORT <-> LINE_PORT, both up."""

    def __init__(self):
        if shutil.which("ip") is None:
            raise LinkUnavailable("no `ip` command (iproute2) to make a network namespace")
        self.name = f"ecat-{secrets.token_hex(4)}"
        self.master_port, self.line_port = MASTER_PORT, LINE_PORT
        made = _ip("netns", "add", self.name)
        if made.returncode:
            raise LinkUnavailable(f"cannot make a network namespace: {made.stderr.strip()}")
        try:
            veth = _ip("-n", self.name, "link", "add", MASTER_PORT, "type", "veth", "peer",
                       "name", LINE_PORT)
            if veth.returncode:
                raise LinkUnavailable(f"cannot make a veth pair: {veth.stderr.strip()}")
            for port in (MASTER_PORT, LINE_PORT):
                _ip("-n", self.name, "link", "set", port, "up")
            with self.entered():
                import socket
                try:
                    socket.socket(socket.AF_PACKET, socket.SOCK_RAW).close()
                except OSError as exc:
                    raise LinkUnavailable(f"no raw packet sockets: {exc}") from None
        except BaseException:
            self.close()
            raise

    @contextlib.contextmanager
    def entered(self) -> Iterator[None]:
        """This thread inside the namespace for the block."""
        libc = ctypes.CDLL(None, use_errno=True)
        with _setns_lock, open("/proc/thread-self/ns/net") as home, \
                open(f"/run/netns/{self.name}") as target:
            if libc.setns(target.fileno(), CLONE_NEWNET):
                raise LinkUnavailable(f"setns: {os.strerror(ctypes.get_errno())}")
            try:
                yield
            finally:
                if libc.setns(home.fileno(), CLONE_NEWNET):
                    raise OSError(ctypes.get_errno(), "setns back to the caller's namespace")

    def close(self) -> None:
        _ip("netns", "del", self.name)

    def __enter__(self) -> "VirtualLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class NamespacePair:
    """Two network namespaces of our own, master side and line side, joined by one veth per
    interface name in `interfaces`, each end named the same in its namespace (as a robot file
    names its lines: `ethercat:eth1` on the robot PC and on the drives' side alike). Commands
    run in one with `command(side, argv)`; both are deleted on close."""

    def __init__(self, interfaces: list[str]):
        if shutil.which("ip") is None:
            raise LinkUnavailable("no `ip` command (iproute2) to make a network namespace")
        token = secrets.token_hex(3)
        self.master, self.line = f"ecat-m-{token}", f"ecat-s-{token}"
        made = []
        try:
            for name in (self.master, self.line):
                result = _ip("netns", "add", name)
                if result.returncode:
                    raise LinkUnavailable(f"cannot make a network namespace: "
                                          f"{result.stderr.strip()}")
                made.append(name)
            for k, interface in enumerate(interfaces):
                peer = f"ecatpeer{k}"
                for args in (("-n", self.master, "link", "add", interface, "type", "veth",
                              "peer", "name", peer, "netns", self.line),
                             ("-n", self.line, "link", "set", peer, "name", interface),
                             ("-n", self.master, "link", "set", interface, "up"),
                             ("-n", self.line, "link", "set", interface, "up")):
                    result = _ip(*args)
                    if result.returncode:
                        raise LinkUnavailable(f"cannot make the veth for {interface}: "
                                              f"{result.stderr.strip()}")
        except BaseException:
            for name in made:
                _ip("netns", "del", name)
            raise

    def command(self, side: str, argv: list[str]) -> list[str]:
        """`argv` run inside the `side` namespace ('master' or 'line')."""
        return ["ip", "netns", "exec", getattr(self, side), *argv]

    def close(self) -> None:
        for name in (self.master, self.line):
            _ip("netns", "del", name)

    def __enter__(self) -> "NamespacePair":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=10)


class SlaveProcess:
    """`count` virtual drives as a line of slaves on the link's line port, in their own
    process. `report()` stops them and returns each one's end state; `kill()` is a power cut."""

    def __init__(self, link: VirtualLink, count: int, model: ActuatorModel,
                 payload: Payload = Payload(), noise: SensorNoise = SensorNoise()):
        context = multiprocessing.get_context("spawn")
        self._pipe, child = context.Pipe()
        self.process = context.Process(
            target=_serve_line, args=(link.name, link.line_port, count, model, payload, noise,
                                      child), daemon=True, name="ethercat-line")
        self.process.start()
        child.close()
        if not self._pipe.poll(START_TIMEOUT):
            self.process.kill()
            raise RuntimeError(f"the slave process did not start within {START_TIMEOUT} s")
        try:
            message = self._pipe.recv()
        except EOFError:
            self.process.join(5)
            raise RuntimeError("the slave process died at start (exit code "
                               f"{self.process.exitcode})") from None
        if message != "ready":
            self.process.join(5)
            raise RuntimeError(f"the slave process failed: {message}")

    def kill(self) -> None:
        self.process.kill()
        self.process.join(10)

    def report(self) -> list[dict]:
        os.kill(self.process.pid, signal.SIGTERM)
        if not self._pipe.poll(20):
            raise RuntimeError("no report from the slave process")
        report = self._pipe.recv()
        self.process.join(10)
        return report

    def close(self) -> None:
        if self.process.is_alive():
            self.process.kill()
        self.process.join(10)
        self._pipe.close()

    def __enter__(self) -> "SlaveProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _serve_line(namespace: str, port: str, count: int, model: ActuatorModel, payload: Payload,
                noise: SensorNoise, pipe) -> None:
    """The slave process: into the namespace, the drives on the port until SIGTERM, then the
    end state of every slave down the pipe."""
    from sim_bus.ethercat.segment import serve
    from sim_bus.priority import answer_like_hardware

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    answer_like_hardware()  # not permitted: the line still works, SOEM retrying more often
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        with open(f"/run/netns/{namespace}") as target:
            if libc.setns(target.fileno(), CLONE_NEWNET):
                raise OSError(ctypes.get_errno(), "setns")
        devices = [Cia402Device(model, payload, SensorNoise(noise.current, noise.joint_torque,
                                                            None if noise.seed is None
                                                            else noise.seed + k))
                   for k in range(count)]
        # the start-up heap collected once and frozen for the process's life, as `sim-bus`
        # does (`driver.clock.collector_off_the_cycle`): a full collection of it takes 73 ms
        # here, and one that came during a master's scan lost its frames (KickCAT waits 10 ms
        # for each: "Error while fetching eeprom data", once in this project's suite)
        gc.collect()
        gc.freeze()
        segment = serve(port, devices, stop, on_ready=lambda _: pipe.send("ready"))
    except Exception as exc:  # the parent raises it with the reason
        pipe.send(f"{type(exc).__name__}: {exc}")
        return
    pipe.send(segment.report())
