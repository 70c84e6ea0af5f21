"""`--can-log` reads as a capture of the wire would: every frame after the one it answers
(the drive's TPDOs after their SYNC, within that SYNC's cycle), stamped on the run's time base
(a lock-step log replays at the drive's pace, SYNCs one period apart)."""

import queue
import subprocess
import sys
import threading

import can
import pytest

from protocol import pdo
from robot.can_log import CanLog, LoggedBus

NODE = 2
SYNC = 0x80
TPDOS = [layout.cob_id(NODE) for layout in pdo.DEFAULT_TPDOS]
RPDO = pdo.RPDO_COMMAND.cob_id(NODE)


def cycles_of(frames: list[can.Message]) -> list[list[can.Message]]:
    """The frames from each SYNC up to the next (the first SYNC starts the first cycle)."""
    cycles: list[list[can.Message]] = []
    for frame in frames:
        if frame.arbitration_id == SYNC:
            cycles.append([])
        if cycles:
            cycles[-1].append(frame)
    return cycles


@pytest.mark.subprocess
def test_a_lockstep_sim_log_puts_each_answer_after_its_sync_on_drive_time(tmp_path):
    path = tmp_path / "run.log"  # candump, what `candump -l` writes and can.LogReader reads
    proc = subprocess.run([sys.executable, "-m", "commands.actuatord", "--sim", "--lockstep",
                           "--duration", "1", "--no-multicast-scouting", "--can-log",
                           str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    frames = list(can.LogReader(path))
    cycles = cycles_of(frames)
    assert len(cycles) >= 999
    for cycle in cycles[:-1]:  # the last SYNC may be the one the run stopped after
        sync = cycle[0]
        rest = [f for f in cycle[1:] if f.arbitration_id in (*TPDOS, RPDO)]  # no heartbeats
        # the three TPDOs answer this SYNC (TPDO1 echoes its counter), then the command goes
        assert [f.arbitration_id for f in rest[:3]] == TPDOS, [hex(f.arbitration_id)
                                                               for f in cycle]
        echo = pdo.decode(pdo.DEFAULT_TPDOS[0], rest[0].data)[pdo.SYNC_ECHO.index]
        assert echo == sync.data[0]
        assert RPDO in [f.arbitration_id for f in rest[3:]]
    stamps = [f.timestamp for f in frames]
    assert stamps == sorted(stamps)
    syncs = [cycle[0].timestamp for cycle in cycles]
    # drive time: one period between SYNCs (candump keeps microseconds), so 1 s of drive
    # time replays in 1 s however fast lock-step ran it
    assert all(abs(b - a - 1e-3) < 2e-6 for a, b in zip(syncs, syncs[1:], strict=False))


class _AnsweringBus(can.BusABC):
    """A bus on which a device answers every frame at once: its answer reaches the receive
    thread before `send` returns (as a fast drive on udp_multicast can)."""

    def __init__(self) -> None:
        super().__init__(channel="answering")
        self._answers: list[can.Message] = []
        self._available = threading.Condition()
        self.received = threading.Event()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        with self._available:
            self._answers.append(can.Message(arbitration_id=TPDOS[0], data=bytes(7),
                                             is_extended_id=False))
            self._available.notify()
        self.received.wait(2)  # the receive thread holds the answer before we return
        self.received.clear()

    def _recv_internal(self, timeout: float | None):
        with self._available:
            if not self._answers and not self._available.wait(timeout):
                return None, False
            answer = self._answers.pop(0)
        self.received.set()
        return answer, False


def test_an_answer_received_while_its_question_is_sent_is_logged_after_it(tmp_path):
    path = tmp_path / "bus.log"
    log = CanLog(str(path), "answering")
    bus = LoggedBus(_AnsweringBus(), log)
    got: queue.Queue = queue.Queue()
    reader = threading.Thread(target=lambda: [got.put(bus.recv(2)) for _ in range(5)])
    reader.start()
    for counter in range(1, 6):  # a master's cycle: the SYNC, then wait for its answer
        bus.send(can.Message(arbitration_id=SYNC, data=[counter], is_extended_id=False))
        assert got.get(timeout=5) is not None
    reader.join(10)
    bus.shutdown()
    log.stop()
    order = [f.arbitration_id for f in can.LogReader(path)]
    assert order == [SYNC, TPDOS[0]] * 5
