import contextlib
import fcntl
import os
import random
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

import can
import canopen
import pytest
from can.interfaces.udp_multicast import UdpMulticastBus

from driver.canopen_drive import CanOpenDrive
from driver.clock import clock_for
from model.parameters import Payload, load_model
from protocol.bus_spec import parse_bus_spec
from sim_bus.embedded import EmbeddedDrive
from sim_bus.ethercat.netns import LinkUnavailable, VirtualLink
from sim_bus.plant import SensorNoise


@contextmanager
def virtual_pair(payload: Payload = Payload(), noise: SensorNoise = SensorNoise(), model=None,
                 lockstep: bool = True, **drive_kwargs):
    """A virtual drive (its CANopen node; the device is `sim.device`) and our master, linked
    as `--sim` links them: each frame is delivered in its sender's thread, so a SYNC comes back
    with its TPDOs before `send` returns and no thread scheduling can delay an answer. Lock-step
    by default: both sides' watchdogs count cycles, so a busy host cannot trip them."""
    model = model or load_model()
    embedded = EmbeddedDrive(model, payload, noise, 2, clock=clock_for(lockstep))
    master = CanOpenDrive(embedded.master_network, 2, velocity_limit=model.limits.velocity_max,
                          drive_gain=model.parameters.drive_gain,
                          clock=clock_for(lockstep),
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


def wait_for(condition: Callable[[], object], timeout: float, poll: float = 0.005) -> bool:
    """Whether `condition()` came true within `timeout` s of the wall clock, looked at every
    `poll` s and once more at the end: the bound for what another thread or process does
    (a frame delivered, a file grown), which no drive time paces. A test asserts the result,
    so a timeout fails it where it waited, not later on a value never set."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(poll)
    return bool(condition())


def _ephemeral_floor() -> int:
    """The first port of the kernel's ephemeral range (Linux's default where it cannot be
    read)."""
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def udp_port() -> int:
    """A port for a test's udp_multicast bus, below the kernel's ephemeral range. The lean
    multicast networks send from sockets on ephemeral ports, and a bus whose port one of them
    holds (another process's, the moment it starts) is refused: "could not create or
    configure socket", one sim-bus of ten in a CI run when ports were drawn up to 60000."""
    return random.randint(10000, max(10001, _ephemeral_floor() - 1))


def udp_bus_spec() -> str:
    """A multicast group and port of our own, so parallel runs do not hear each other."""
    return f"udp_multicast:239.0.0.{random.randint(1, 250)}:{udp_port()}"


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


@contextmanager
def soem_waiting_us(timeout_us: int):
    """SOEM waiting `timeout_us` for each frame while the block runs (its return timeout,
    process-wide), as this project's master does while configuring a line
    (`driver.ethercat_master.CONFIGURING_RETURN_TIMEOUT_US`), for a test that drives bare
    pysoem. SOEM's default, 2 ms, is below this host's own stalls (5-10 ms a few times a
    minute, both CPUs at once: the KickCAT test's LINK_TIMEOUT) and below what a master at
    normal priority waits for the CPU beside two busy loops, and a frame late behind one
    breaks an exchange: an entry's name came back empty in an SDO Information browse (the
    test alone on a quiet host), a slave's SII identity read as 0 beside two busy loops (the
    master's own measured case: a stale mailbox answer the next read takes for its own).
    Beside busy loops it is not enough: with it, one configuration in six still summed a
    PDO entry short (config_map 42 bytes for 44) beside two, and the SII/mapping and SDO
    Information tests failed 2 runs in 24 beside four (a slave's name read as 'Virtua', an
    entry's name empty), at the real-time master's priority as well (2 in 24: not kept). The
    stalls there are the virtual machine's, not this process's: a SCHED_RR 49 loop on each
    CPU (`driver.host_floor.FloorBeside`) woke 5-84 ms late 9 times in a minute beside three
    busy loops, against once beside one (a second pair of minutes: 2 against 0), and SOEM's
    timers (this wait, its 20 ms EEPROM and mailbox waits) run on the wall clock."""
    import pysoem

    returning = pysoem.settings.timeouts.ret
    pysoem.settings.timeouts.ret = timeout_us
    try:
        yield
    finally:
        pysoem.settings.timeouts.ret = returning


@contextmanager
def as_a_real_time_master():
    """This test process's threads at the real-time master's priority (SCHED_RR, as
    `actuatord` takes it) while a test plays a real-time master itself, then back to normal:
    at normal priority on a loaded host the test's own cycle stalled past the drive's 100 ms
    watchdog and the drive, rightly, stopped obeying (1 run in 3 at load 4-7)."""
    from driver.clock import REAL_TIME_PRIORITY

    threads = [int(tid) for tid in os.listdir("/proc/self/task")]
    try:
        for tid in threads:
            # a thread of an earlier test may end between the listing and here
            with contextlib.suppress(ProcessLookupError):
                os.sched_setscheduler(tid, os.SCHED_RR, os.sched_param(REAL_TIME_PRIORITY))
    except PermissionError:
        pass  # not root: the test runs at normal priority
    try:
        yield
    finally:
        for tid in threads:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))


@contextmanager
def virtual_drive_process(bus: str, node_id: int = 2, *extra: str):
    """A virtual drive in its own process (`tests.virtual_drive_process`), booted."""
    proc = subprocess.Popen([sys.executable, "-m", "tests.virtual_drive_process", bus,
                             str(node_id), *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert "ready" in line, f"drive did not start: {line!r} {proc.stderr.read()}"
        yield proc
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()


class CanSemanticsBus(UdpMulticastBus):
    """python-can's udp_multicast hands a sender its own frames back, which a CAN controller
    does not: this bus drops every frame whose identifier it has sent itself."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._sent: set[int] = set()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._sent.add(msg.arbitration_id)
        super().send(msg, timeout)

    def _recv_internal(self, timeout: float | None):
        msg, filtered = super()._recv_internal(timeout)
        if msg is not None and msg.arbitration_id in self._sent:
            return None, filtered
        return msg, filtered


def can_semantics_network(bus_spec: str) -> canopen.Network:
    """A connected canopen Network on a udp_multicast bus spec, with CAN semantics."""
    kwargs = parse_bus_spec(bus_spec)
    bus = CanSemanticsBus(channel=kwargs["channel"], port=kwargs["port"])
    return canopen.Network(bus).connect()


@pytest.fixture
def link():
    """A virtual EtherCAT cable of the test's own (a network namespace with a veth pair,
    removed afterwards); the test is skipped, saying why, where the kernel or the privileges
    cannot make one."""
    try:
        virtual = VirtualLink()
    except LinkUnavailable as exc:
        pytest.skip(str(exc))
    with virtual:
        yield virtual


# what the controller runs before the workers start (`pytest_configure`), each in a process of
# its own, side by side: between them they compile (a first run) or load what these commands
# compile before their drives run (solver, loop, bus and line kernels, physics, tracking law);
# the veth line's own kernels are left to the tests that start one
WARM_UP = (
    ("commands.actuatord", "--sim", "--lockstep", "--duration", "0.01",
     "--no-multicast-scouting"),
    ("commands.actuatord", "--sim", "--lockstep", "--robot", "talos_32", "--duration", "0.01",
     "--no-multicast-scouting"),
    ("commands.recorder", "--sinusoid", "--sim", "--lockstep", "--duration", "0.5",
     "--no-progress", "-o", "{folder}/warm-up.mcap"),
)

# s: the warm-up's limit (a first run's compile took 50 s here, 95 s beside two busy loops)
WARM_UP_TIMEOUT = 600.0


def pytest_xdist_auto_num_workers(config) -> int:
    """`-n auto` (pyproject.toml's default): two workers, one on a single CPU. Two is what the
    suite's figures were measured with on a 2-core host; the real-time tests and those that
    start processes of their own assume a core to spare beside each worker."""
    return min(2, os.cpu_count() or 1)


def pytest_configure(config) -> None:
    """On pytest-xdist workers (`-n auto`, the default in pyproject.toml) the controller compiles
    first, once, before any worker starts. Otherwise the first test on each worker to run a
    command compiles it (30-60 s, both at once), and a test that counts a command's stderr lines
    finds the first run's notice among them, or not, by which worker got which file first.
    A warm-up that fails or outlasts WARM_UP_TIMEOUT says why here (stopped, in the second
    case) and the tests then fail on their own."""
    if (not getattr(config.option, "numprocesses", None) or hasattr(config, "workerinput")
            or config.option.collectonly):
        return
    started = time.monotonic()
    with tempfile.TemporaryDirectory() as folder:
        runs = [subprocess.Popen([sys.executable, "-m", *(arg.format(folder=folder)
                                                          for arg in command)],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
                for command in WARM_UP]
        for command, run in zip(WARM_UP, runs, strict=True):
            try:
                _, err = run.communicate(timeout=max(1.0, started + WARM_UP_TIMEOUT
                                                     - time.monotonic()))
            except subprocess.TimeoutExpired:
                run.kill()
                _, err = run.communicate()
                err += f"(stopped: still running after {WARM_UP_TIMEOUT:.0f} s)"
            if run.returncode != 0:
                sys.stderr.write(f"warm-up {' '.join(command)} failed:\n{err}\n")
    sys.stderr.write(f"warm-up: {time.monotonic() - started:.1f} s before the workers "
                     "started\n")


_exit_status: list[int] = []


def pytest_sessionfinish(session, exitstatus) -> None:
    _exit_status.append(int(exitstatus))


def pytest_unconfigure(config) -> None:
    """A thread that is not a daemon (an unclosed Zenoh session's callback thread, say) would
    keep this process alive after the summary, and CI would wait for it until its time limit.
    Such threads are named on stderr and the process ends with the session's own status."""
    import os
    import threading

    stray = [t for t in threading.enumerate()
             if t is not threading.main_thread() and not t.daemon and t.is_alive()]
    for thread in stray:
        thread.join(2.0)
    stray = [t for t in stray if t.is_alive()]
    if stray:
        sys.stderr.write("tests left threads that would keep the process alive: "
                         + ", ".join(t.name for t in stray) + "\n")
        sys.stderr.flush()
        sys.stdout.flush()
        os._exit(_exit_status[-1] if _exit_status else 1)


# taken exclusively by a test marked real_time while it runs, shared by every other test,
# whichever process runs them; the turnstile: held by a real_time test waiting for the lock,
# so that no other test starts meanwhile
REAL_TIME_LOCK = Path(tempfile.gettempdir()) / "actuator-link-tests-real-time.lock"
TURNSTILE = Path(tempfile.gettempdir()) / "actuator-link-tests-turnstile.lock"


@contextmanager
def holding_the_test_lock(alone: bool):
    """REAL_TIME_LOCK held while the block runs: exclusively (`alone`: a real_time test) or
    shared (any other work of the suite), taking TURNSTILE first, so that a real_time test
    waiting is not kept out for ever by the others taking turns with the lock shared. Not
    nested: a holder that asks again waits behind a real_time test that waits for it."""
    with REAL_TIME_LOCK.open("a") as lock, TURNSTILE.open("a") as turnstile:
        fcntl.flock(turnstile, fcntl.LOCK_EX)
        if alone:
            fcntl.flock(lock, fcntl.LOCK_EX)
            fcntl.flock(turnstile, fcntl.LOCK_UN)
        else:
            fcntl.flock(turnstile, fcntl.LOCK_UN)
            fcntl.flock(lock, fcntl.LOCK_SH)
        yield  # both released as the files close


@pytest.fixture(autouse=True)
def real_time_tests_alone(request):
    """A test marked real_time runs alone (`holding_the_test_lock`): holding REAL_TIME_LOCK
    exclusively, while every other test, and every module or session fixture that keeps the
    CPUs busy while it sets up (those set up before this one), holds it shared. So none
    runs beside it, on another pytest-xdist worker (`-n auto`, pyproject.toml) or in another
    test run on this host. What runs beside one breaks it: many tests start `sim-bus` or a
    virtual line, which serve at real-time priority (`sim_bus.priority`) and, serving a
    lock-step master, keep a core busy. Beside such a test, the KickCAT test's master lost a
    frame for 10 ms, in a clean clone's two-worker run; beside a fixture's two lock-step
    recorders, a drive's 0.5 s master-silence watch ended a refused-master test's drive
    before it was looked at; two real-time loops at real-time priority on two cores each
    miss the other's deadlines; and a second holder of the CPU latency request hides the
    first's. Locks, not xdist's groups: `--dist loadgroup` stopped grouping with pytest 9.2
    (pytest-xdist issue 1386), silently. Autouse, so it is taken before the test's own
    function fixtures start any process."""
    with holding_the_test_lock(alone=request.node.get_closest_marker("real_time") is not None):
        yield
