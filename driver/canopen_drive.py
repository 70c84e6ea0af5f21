"""CiA 402 master over CANopen (canopen + python-can): boot by NMT, map PDOs by SDO, produce
SYNC, enable, sample, command current, and watch heartbeat and EMCY."""

import logging
import math
import threading
import time

import can
import canopen
from canopen.emcy import EmcyError
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from driver.interface import (
    CommandRangeError,
    Drive,
    DriveError,
    DriveFault,
    DriveLost,
    DriveTimeout,
    EncoderGlitch,
    Sample,
)
from protocol import cia301, cia402, eds_path, objects
from protocol import pdo as pdo_layout
from protocol.bus_spec import parse_bus_spec
from protocol.cia402 import State

log = logging.getLogger(__name__)

SYNC_COB_ID = 0x80
SYNC_COUNTER_MAX = 240  # CiA 301 synchronous counter range
HEARTBEAT_BASE = 0x700
DEFAULT_HEARTBEAT_MS = 100
NOTIFIER_CYCLE = 0.05  # s; bounds how long closing the network waits for the receive thread
ENABLE_STEP_TIMEOUT = 0.5  # s for the drive to show each CiA 402 transition
# 20 rad/s at 1 kHz: four times the elbow's velocity limit; a bigger step is not motion
MAX_POSITION_STEP = 0.02  # rad per cycle
# a 1 Mbit/s CAN bus carries at most ~8 full frames per millisecond: far more is a flood
MAX_FRAMES_PER_CYCLE = 32
SENSOR_CEILING = 2**31 - 1  # the INT32 limits of a reading mean "saturated"


def open_network(bus_spec: str) -> canopen.Network:
    """A connected canopen Network for a bus spec (see protocol.bus_spec)."""
    network = canopen.Network()
    network.NOTIFIER_CYCLE = NOTIFIER_CYCLE
    network.connect(**parse_bus_spec(bus_spec))
    return network


class CanOpenDrive(Drive):
    """One CiA 402 drive on a CANopen network, this process being the master.

    The drive owns `network` and disconnects it on close. The master owns the SYNC: `sync()`
    sends one SYNC and waits for every mapped TPDO of that cycle, so in lock-step simulation
    time advances exactly one period per call and on real hardware the caller's timer sets
    the rate.
    """

    def __init__(self, network: canopen.Network, node_id: int = 2, period: float = 1e-3,
                 heartbeat_ms: int = DEFAULT_HEARTBEAT_MS, response_timeout: float = 1.0,
                 heartbeat_timeout_factor: float = 2.0):
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id} outside 1..127")
        if not 50e-6 <= period <= 1.0:
            raise ValueError(f"period {period} s outside 50 us .. 1 s")
        self.network = network
        self.node_id = node_id
        self.period = period
        self.heartbeat_ms = heartbeat_ms
        self.heartbeat_timeout = heartbeat_timeout_factor * heartbeat_ms / 1000.0
        self.response_timeout = response_timeout
        self.node = canopen.RemoteNode(node_id, str(eds_path()))
        network.add_node(self.node)
        self.current_limit = 0.0
        self.cycle = 0
        self.last_emcy: EmcyError | None = None
        self.fault: DriveError | None = None
        self._controlword = 0
        self._tpdos = {layout.cob_id(node_id): layout for layout in pdo_layout.DEFAULT_TPDOS}
        self._rpdo = pdo_layout.RPDO_COMMAND
        self._values: dict[int, int] = {}
        self._pending: set[int] = set()
        self._sync_counter = 0  # 1..240 in each SYNC (CiA 301), echoed by the drive in TPDO1
        self._cycle_open = False
        self._arrived = threading.Condition()
        self._latest: Sample | None = None
        self._last_heartbeat: float | None = None
        self._watchdog_stop = threading.Event()
        self._watchdog: threading.Thread | None = None
        self._started = False
        self._booted = threading.Event()  # set by the boot-up message (heartbeat state 0)
        self.max_position_step = MAX_POSITION_STEP * period / 1e-3
        self._warnings: list[str] = []
        self.unexpected_tpdos = 0
        self._frames = 0
        self._frames_at_sync = 0
        network.subscribe(HEARTBEAT_BASE + node_id, self._on_heartbeat)
        self.node.emcy.add_callback(self._on_emcy)
        for cob_id in self._tpdos:
            network.subscribe(cob_id, self._on_tpdo)
        if network.notifier is not None:
            network.notifier.add_listener(_FrameCounter(self))

    @classmethod
    def open(cls, bus_spec: str, node_id: int = 2, **kwargs) -> "CanOpenDrive":
        return cls(open_network(bus_spec), node_id, **kwargs)

    # --- bring-up ---------------------------------------------------------------------------

    def start(self) -> None:
        self.boot()
        self.configure()
        self.node.nmt.state = "OPERATIONAL"
        self.enable()
        self._started = True
        self._frames_at_sync = self._frames  # bring-up traffic is not load

    def boot(self, timeout: float = 5.0) -> None:
        """NMT reset communication and wait for the boot-up message."""
        self._booted.clear()
        self.node.nmt.state = "RESET COMMUNICATION"
        if not self._booted.wait(timeout):
            raise DriveLost(f"node {self.node_id}: no boot-up message within {timeout} s "
                            "(is the drive powered and on this bus?)")
        self._last_heartbeat = time.monotonic()

    def configure(self) -> None:
        """Write cycle period, heartbeat, mode and the default PDO layout by SDO (pre-op)."""
        sdo = self.node.sdo
        try:
            sdo[objects.CYCLE_PERIOD_US].raw = int(round(self.period * 1e6))
            sdo[objects.PRODUCER_HEARTBEAT_MS].raw = self.heartbeat_ms
            sdo[objects.MODES_OF_OPERATION].raw = objects.MODE_CYCLIC_SYNC_CURRENT
            for n, layout in enumerate(pdo_layout.DEFAULT_RPDOS):
                self._write_pdo(objects.RPDO_COMM + n, objects.RPDO_MAP + n, layout,
                                cia301.TRANSMISSION_ASYNC)
            for n, layout in enumerate(pdo_layout.DEFAULT_TPDOS):
                self._write_pdo(objects.TPDO_COMM + n, objects.TPDO_MAP + n, layout,
                                cia301.TRANSMISSION_SYNC)
            for n in range(len(pdo_layout.DEFAULT_TPDOS), 4):
                cob_id = sdo[objects.TPDO_COMM + n][1].raw
                sdo[objects.TPDO_COMM + n][1].raw = cob_id | 0x80000000
            rated = sdo[objects.RATED_CURRENT].raw / objects.MILLI
            self.current_limit = sdo[objects.MAX_CURRENT].raw / objects.MILLI * rated
        except (SdoAbortedError, SdoCommunicationError) as exc:
            raise DriveError(f"node {self.node_id}: configuration by SDO failed: {exc}") from exc
        self._start_watchdog()

    def _write_pdo(self, comm: int, mapping: int, layout: pdo_layout.PdoLayout,
                   transmission: int) -> None:
        sdo = self.node.sdo
        cob_id = layout.cob_id(self.node_id)
        sdo[comm][1].raw = cob_id | 0x80000000
        sdo[comm][2].raw = transmission
        sdo[mapping][0].raw = 0
        for k, obj in enumerate(layout.objects, start=1):
            sdo[mapping][k].raw = obj.mapping_entry
        sdo[mapping][0].raw = len(layout.objects)
        sdo[comm][1].raw = cob_id

    # --- CiA 402 ----------------------------------------------------------------------------

    def state(self) -> State:
        return cia402.state_from_statusword(self._sdo_read(objects.STATUSWORD))

    def enable(self) -> None:
        self._steer(State.OPERATION_ENABLED)
        self.fault = None

    def disable(self) -> None:
        self._send_command(cia402.Command.DISABLE_VOLTAGE.value, 0.0)
        self._steer(State.SWITCH_ON_DISABLED)

    def fault_reset(self) -> None:
        self._sdo_write(objects.CONTROLWORD, 0)
        self._steer(State.SWITCH_ON_DISABLED)
        self.last_emcy = None
        self.fault = None

    def _steer(self, goal: State) -> None:
        """Walk the CiA 402 graph by SDO controlword writes until the statusword shows goal."""
        for _ in range(8):
            state = self.state()
            controlword = cia402.controlword_toward(state, goal)
            if controlword is None:
                self._controlword = (cia402.Command.ENABLE_OPERATION.value
                                     if goal is State.OPERATION_ENABLED else 0)
                return
            if controlword == cia402.Command.FAULT_RESET.value:
                self._sdo_write(objects.CONTROLWORD, 0)
            self._sdo_write(objects.CONTROLWORD, controlword)
            deadline = time.monotonic() + ENABLE_STEP_TIMEOUT
            while self.state() is state and time.monotonic() < deadline:
                time.sleep(0.001)
        raise DriveFault(f"node {self.node_id}: cannot reach '{goal.value}' "
                         f"(stuck in '{self.state().value}')")

    # --- cyclic -----------------------------------------------------------------------------

    def sync(self) -> Sample:
        self._raise_if_unhealthy()
        with self._arrived:
            self._pending = set(self._tpdos)
            self._sync_counter = self._sync_counter % SYNC_COUNTER_MAX + 1
            self._cycle_open = False
        self.network.send_message(SYNC_COB_ID, bytes([self._sync_counter]))
        with self._arrived:
            arrived = self._arrived.wait_for(
                lambda: not self._pending or self.fault is not None, self.response_timeout)
            if self.fault is not None and self._pending:
                raise self.fault  # a reboot, EMCY or lost heartbeat ended the wait
            if not arrived:
                missing = ", ".join(f"0x{c:03X}" for c in sorted(self._pending))
                error = DriveTimeout(f"node {self.node_id}: no TPDO {missing} within "
                                     f"{self.response_timeout * 1e3:.0f} ms of SYNC "
                                     f"{self.cycle + 1}")
                self.fault = error
                raise error
            values = dict(self._values)
        self.cycle += 1
        frames, self._frames_at_sync = self._frames - self._frames_at_sync, self._frames
        if frames > MAX_FRAMES_PER_CYCLE:
            self._warnings.append(f"bus overloaded: {frames} frames in one cycle (at most "
                                  f"{MAX_FRAMES_PER_CYCLE} expected)")
        reading = values[objects.JOINT_TORQUE_SENSOR]
        joint_torque = reading / objects.MILLI
        if abs(reading) >= SENSOR_CEILING:
            joint_torque = math.nan
            self._warnings.append(f"joint torque sensor reading saturated ({reading} mN.m)")
        sample = Sample(
            t=self.cycle * self.period,
            position=objects.increments_to_position(values[objects.POSITION_ACTUAL]),
            velocity=objects.increments_to_position(values[objects.VELOCITY_ACTUAL]),
            motor_current=values[objects.MOTOR_CURRENT_ACTUAL] / objects.MILLI,
            joint_torque=joint_torque,
            statusword=values[objects.STATUSWORD],
        )
        previous, self._latest = self._latest, sample
        if previous is not None and abs(sample.position - previous.position) > (
                self.max_position_step):
            error = EncoderGlitch(
                f"node {self.node_id}: position jumped {sample.position - previous.position:+.4f}"
                f" rad in one cycle (at most {self.max_position_step} rad is motion): encoder "
                "glitch")
            self.fault = error
            raise error
        if cia402.state_from_statusword(sample.statusword) is State.FAULT and self.fault is None:
            self.fault = DriveFault(self._fault_text(), self._emcy_code())
        return sample

    def read(self) -> Sample | None:
        return self._latest

    def warnings(self) -> list[str]:
        out, self._warnings = self._warnings, []
        return out

    def command_current(self, current: float) -> None:
        if not isinstance(current, int | float) or not math.isfinite(current):
            raise CommandRangeError(f"motor current command {current!r} is not a finite number")
        if abs(current) > self.current_limit:
            raise CommandRangeError(f"motor current command {current:.3f} A outside the drive's "
                                    f"limit of +/-{self.current_limit:.3f} A")
        self._raise_if_unhealthy()
        self._send_command(cia402.Command.ENABLE_OPERATION.value, current)

    def _send_command(self, controlword: int, current: float) -> None:
        self._controlword = controlword
        payload = pdo_layout.encode(self._rpdo, {
            objects.CONTROLWORD: controlword,
            objects.TARGET_CURRENT: objects.amps_to_milliamps(current)})
        self.network.send_message(self._rpdo.cob_id(self.node_id), payload)

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        layout = self._tpdos[can_id]
        try:
            decoded = pdo_layout.decode(layout, bytes(data))
        except ValueError as exc:
            log.warning("node %d: %s", self.node_id, exc)
            return
        with self._arrived:
            if objects.SYNC_ECHO in decoded:
                # the first TPDO names its SYNC; the others follow it in order on the bus
                self._cycle_open = decoded[objects.SYNC_ECHO] == self._sync_counter
            if can_id not in self._pending or not self._cycle_open:
                # a second copy, or a frame from an earlier cycle: never mix it in
                self.unexpected_tpdos += 1
                self._warnings.append(f"unexpected TPDO 0x{can_id:03X} (duplicate or late)")
                return
            self._values.update(decoded)
            self._pending.discard(can_id)
            if not self._pending:
                self._arrived.notify_all()

    # --- health -----------------------------------------------------------------------------

    def _raise_fault(self, error: DriveError) -> None:
        """Record a fault and wake a sync() waiting for TPDOs that will not come."""
        with self._arrived:
            self.fault = error
            self._arrived.notify_all()

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if data and data[0] == 0:
            self._booted.set()
            if self._started:
                self._raise_fault(DriveLost(f"node {self.node_id}: drive rebooted (boot-up "
                                            "message) while in use"))
        self._last_heartbeat = time.monotonic()

    def _on_emcy(self, error: EmcyError) -> None:
        if error.code == cia301.EMCY_NO_ERROR:
            return
        self.last_emcy = error
        log.error("node %d: EMCY 0x%04X %s", self.node_id, error.code, error.get_desc())
        self._raise_fault(DriveFault(self._fault_text(), error.code))

    def _fault_text(self) -> str:
        if self.last_emcy is None:
            return f"node {self.node_id}: drive in fault state"
        return (f"node {self.node_id}: drive fault, EMCY 0x{self.last_emcy.code:04X} "
                f"({self.last_emcy.get_desc()})")

    def _emcy_code(self) -> int:
        return self.last_emcy.code if self.last_emcy is not None else 0

    def _start_watchdog(self) -> None:
        if self._watchdog is not None:
            return
        self._watchdog = threading.Thread(target=self._watch_heartbeat, daemon=True,
                                          name=f"heartbeat-watch-{self.node_id}")
        self._watchdog.start()

    def _watch_heartbeat(self) -> None:
        """Heartbeat consumer (CiA 301 0x1016 semantics): declares the drive lost when no
        heartbeat came for heartbeat_timeout; polls at a quarter of the producer period."""
        poll = self.heartbeat_ms / 4000.0
        while not self._watchdog_stop.wait(poll):
            last = self._last_heartbeat
            if last is None or self.fault is not None:
                continue
            silent = time.monotonic() - last
            if silent > self.heartbeat_timeout:
                self._raise_fault(DriveLost(f"node {self.node_id}: heartbeat missing for "
                                            f"{silent * 1e3:.0f} ms (producer period "
                                            f"{self.heartbeat_ms} ms)"))
                log.error("%s", self.fault)

    def _raise_if_unhealthy(self) -> None:
        if self.fault is not None:
            raise self.fault

    def _sdo_read(self, index: int) -> int:
        try:
            return self.node.sdo[index].raw
        except (SdoAbortedError, SdoCommunicationError) as exc:
            raise DriveError(f"node {self.node_id}: SDO read 0x{index:04X} failed: {exc}") from exc

    def _sdo_write(self, index: int, value: int) -> None:
        try:
            self.node.sdo[index].raw = value
        except (SdoAbortedError, SdoCommunicationError) as exc:
            raise DriveError(f"node {self.node_id}: SDO write 0x{index:04X} failed: {exc}") \
                from exc

    # --- shutdown ---------------------------------------------------------------------------

    def close(self) -> None:
        """Leave the drive disabled: zero current by RPDO, disable voltage by SDO, NMT pre-op.
        Each step is best effort so a dead drive does not stop the rest. Idempotent."""
        if self._watchdog_stop.is_set():
            return
        self._watchdog_stop.set()
        try:
            self._send_command(cia402.Command.DISABLE_VOLTAGE.value, 0.0)
            self.node.sdo[objects.CONTROLWORD].raw = cia402.Command.DISABLE_VOLTAGE.value
            self.node.nmt.state = "PRE-OPERATIONAL"
        except (SdoAbortedError, SdoCommunicationError, can.CanError, RuntimeError) as exc:
            log.warning("node %d: could not confirm disable on close: %s", self.node_id, exc)
        finally:
            self.network.disconnect()


class _FrameCounter(can.Listener):
    """Counts every frame on the bus (ours or not) for the overload check."""

    def __init__(self, drive: CanOpenDrive):
        self._drive = drive

    def on_message_received(self, msg: can.Message) -> None:
        self._drive._frames += 1
