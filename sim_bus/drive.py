"""The virtual drive node: canopen's LocalNode (SDO server, NMT slave with heartbeat, EMCY
producer) plus what a CiA 402 drive does on SYNC: latch the command, advance the physics one
period, sample the sensors and send the TPDOs.

Everything runs in the network's receive thread, so a SYNC is handled completely before the
next frame is looked at: lock-step comes for free when the master waits for the TPDOs.
"""

import logging
import threading
import time

import canopen
from canopen.nmt import NmtSlave
from canopen.sdo import SdoAbortedError

from model.parameters import ActuatorModel, Payload
from protocol import cia402, eds_path, objects
from protocol import pdo as pdo_layout
from protocol.cia402 import State
from sim_bus.faults import (
    ENCODER_JUMP,
    FLOOD_COB_ID,
    FLOOD_SECONDS,
    SATURATED_READING,
    TPDO_DELAY,
    Fault,
)
from sim_bus.plant import Plant, SensorNoise

log = logging.getLogger(__name__)

NMT_BOOT_UP_STATE = 0
NMT_PRE_OPERATIONAL = 127
NMT_OPERATIONAL = 5
NMT_RESET_NODE = 129
NMT_RESET_COMMUNICATION = 130
NMT_ENTER_PRE_OPERATIONAL = 128
SYNC_COB_ID = 0x80
SDO_ABORT_VALUE_RANGE = 0x06090030
SDO_ABORT_NOT_MAPPABLE = 0x06040041
SDO_ABORT_PDO_LENGTH = 0x06040042
SDO_ABORT_WRONG_STATE = 0x08000022


class DelayedHeartbeatNmt(NmtSlave):
    """NMT slave whose first heartbeat comes one period after a state change, as on real
    devices. canopen's NmtSlave sends it at once, right behind the boot-up message, and a
    master waiting for the boot-up (canopen's own wait_for_bootup) can miss it in the race."""

    _timer: threading.Timer | None = None

    def start_heartbeat(self, heartbeat_time_ms: int) -> None:
        self.stop_heartbeat()
        self._heartbeat_time_ms = heartbeat_time_ms
        if heartbeat_time_ms > 0:
            self._timer = threading.Timer(heartbeat_time_ms / 1000.0, NmtSlave.start_heartbeat,
                                          (self, heartbeat_time_ms))
            self._timer.daemon = True
            self._timer.start()

    def stop_heartbeat(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        super().stop_heartbeat()


class VirtualDrive:
    """A CiA 402 drive for the elbow, on any canopen Network (virtual, UDP multicast, SocketCAN).

    Modes: -1 cyclic synchronous current (target 0x2000, mA), 10 cyclic synchronous torque
    (target 0x6071, per mille of rated torque). The command is saturated at max current 0x6073;
    above the trip level 0x2003 the drive faults (over-current), as does leaving the software
    position window 0x607D (position-limit fault). Faults send EMCY and zero the current.
    """

    def __init__(self, network: canopen.Network, node_id: int, model: ActuatorModel,
                 payload: Payload = Payload(), noise: SensorNoise = SensorNoise(),
                 initial_position: float | None = None):
        self.network = network
        self.node_id = node_id
        self.model = model
        self.plant = Plant(model.parameters, payload, noise, initial_position)
        self._lock = threading.RLock()
        self.node = canopen.LocalNode(node_id, str(eds_path()))
        stock_nmt = self.node.nmt
        self.node.nmt = DelayedHeartbeatNmt(node_id, self.node)
        self.node._write_callbacks.remove(stock_nmt.on_write)  # 0x1017 writes go to ours
        self.node.add_write_callback(self.node.nmt.on_write)
        self.node.add_read_callback(self._on_sdo_read)
        self.node.add_write_callback(self._on_sdo_write)
        self.state = State.NOT_READY_TO_SWITCH_ON
        self.error_code = objects.EMCY_NO_ERROR
        self.sync_count = 0
        self.applied_current = 0.0
        self._silent = False
        self._pending_faults: dict[int, Fault] = {}  # sync count -> fault
        self._once: set[Fault] = set()  # faults that act on the next sample
        self.injected: list[tuple[int, Fault]] = []  # (sync count, fault) as they happened
        self._rpdo_by_cob: dict[int, pdo_layout.PdoLayout] = {}
        self._tpdos: list[tuple[int, pdo_layout.PdoLayout]] = []
        self._reset_application()
        network.add_node(self.node)
        network.subscribe(0, self._on_nmt)
        network.subscribe(SYNC_COB_ID, self._on_sync)

    # --- life cycle -------------------------------------------------------------------------

    def boot(self) -> None:
        """Power-on: boot-up message, then pre-operational with the heartbeat running."""
        with self._lock:
            self._silent = False
            self.node.nmt.send_command(NMT_RESET_NODE)
            self.node.nmt.send_command(NMT_ENTER_PRE_OPERATIONAL)
            self.state = State.SWITCH_ON_DISABLED

    def schedule(self, fault: Fault, seconds: float) -> None:
        """Inject `fault` when the drive's time (SYNC count x period) reaches `seconds`."""
        with self._lock:
            self._pending_faults[int(round(seconds / self.period))] = fault

    def inject(self, fault: Fault) -> None:
        """Inject `fault` now."""
        with self._lock:
            self.injected.append((self.sync_count, fault))
            if fault is Fault.HEARTBEAT_STOPS:
                # stopping the periodic task can wait up to a period: not in the SYNC handler
                threading.Thread(target=self.stop_heartbeat, daemon=True).start()
            elif fault is Fault.SILENT:
                self.go_silent()
            elif fault is Fault.OVERCURRENT_TRIP:
                self._fault(objects.EMCY_OVERCURRENT, objects.ERROR_REGISTER_CURRENT)
            elif fault is Fault.BUS_FLOOD:
                threading.Thread(target=self._flood, daemon=True, name="bus-flood").start()
            elif fault is Fault.REBOOT:
                self._reboot()
            elif fault is not Fault.NONE:
                self._once.add(fault)

    def _flood(self) -> None:
        end = time.monotonic() + FLOOD_SECONDS
        while time.monotonic() < end:
            self.network.send_message(FLOOD_COB_ID, bytes(8))

    def _reboot(self) -> None:
        """Power glitch: the application and communication restart, boot-up is sent and the
        drive waits, disabled and pre-operational, for a master to bring it up again."""
        self.node.nmt.stop_heartbeat()
        self._stop_pdos()
        self._reset_application()
        self.state = State.SWITCH_ON_DISABLED
        self.node.nmt.send_command(NMT_RESET_NODE)
        self.node.nmt.send_command(NMT_ENTER_PRE_OPERATIONAL)

    def stop_heartbeat(self) -> None:
        """Fault injection: the heartbeat producer dies while the rest keeps working."""
        self.node.nmt.stop_heartbeat()

    def go_silent(self) -> None:
        """Fault injection: the drive disappears from the bus (power loss, cable cut)."""
        with self._lock:
            self._silent = True
            self.node.nmt.stop_heartbeat()
            self.network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)

    def close(self) -> None:
        self.node.nmt.stop_heartbeat()
        self.network.unsubscribe(SYNC_COB_ID, self._on_sync)
        self.network.unsubscribe(0, self._on_nmt)
        self._stop_pdos()

    def _reset_application(self) -> None:
        self.node.data_store.clear()
        self._controlword = 0
        self._mode = objects.MODE_NONE
        self._target_current = 0.0
        self._target_torque_permille = 0
        self.applied_current = 0.0
        self.error_code = objects.EMCY_NO_ERROR
        self._config_dirty = False
        self._sync_echo = 0
        self._measurement = self.plant.measure()
        self._read_configuration()

    def _read_configuration(self) -> None:
        self.rated_current = self._u(objects.RATED_CURRENT) / objects.MILLI
        self.max_current = self._u(objects.MAX_CURRENT) / objects.MILLI * self.rated_current
        self.trip_current = self._u(objects.OVERCURRENT_TRIP) / objects.MILLI
        self.period = self._u(objects.CYCLE_PERIOD_US) * 1e-6
        self.position_window = tuple(
            objects.increments_to_position(self._u(objects.SOFTWARE_POSITION_LIMIT, k))
            for k in (1, 2))

    def _u(self, index: int, subindex: int = 0) -> int:
        obj = self.node.object_dictionary[index]
        if not isinstance(obj, canopen.objectdictionary.ODVariable):
            obj = obj[subindex]
        return obj.decode_raw(self.node.get_data(index, subindex))

    # --- NMT --------------------------------------------------------------------------------

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self._silent or len(data) != 2 or data[1] not in (0, self.node_id):
            return
        command = data[0]
        with self._lock:
            if command in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
                self.node.nmt.stop_heartbeat()
                if command == NMT_RESET_NODE:
                    self._reset_application()
                    self.state = State.SWITCH_ON_DISABLED
                else:
                    self._reset_communication()
                self.node.nmt.send_command(NMT_RESET_NODE)
                self.node.nmt.send_command(NMT_ENTER_PRE_OPERATIONAL)
            if self.node.nmt.state == "OPERATIONAL":
                self._start_pdos()
            else:
                self._stop_pdos()

    def _reset_communication(self) -> None:
        for index in list(self.node.data_store):
            if 0x1000 <= index < 0x2000:
                del self.node.data_store[index]

    def _start_pdos(self) -> None:
        self._stop_pdos()
        self._tpdos = self._configured_pdos(objects.TPDO_COMM, objects.TPDO_MAP, 4)
        self._rpdo_by_cob = dict(self._configured_pdos(objects.RPDO_COMM, objects.RPDO_MAP, 4))
        for cob_id in self._rpdo_by_cob:
            self.network.subscribe(cob_id, self._on_rpdo)

    def _stop_pdos(self) -> None:
        for cob_id in self._rpdo_by_cob:
            self.network.unsubscribe(cob_id, self._on_rpdo)
        self._tpdos = []
        self._rpdo_by_cob = {}

    def _configured_pdos(self, comm: int, mapping: int, count: int):
        """The enabled PDOs as configured in the dictionary now: (COB-ID, layout) pairs."""
        out = []
        for n in range(count):
            if comm + n not in self.node.object_dictionary:
                continue
            cob_id = self._u(comm + n, 1)
            if cob_id & 0x80000000:
                continue
            entries = [self._u(mapping + n, k) for k in range(1, self._u(mapping + n, 0) + 1)]
            objects = tuple(pdo_layout.object_from_mapping_entry(e) for e in entries)
            out.append((cob_id & 0x7FF, pdo_layout.PdoLayout(0, objects)))
        return out

    # --- SDO --------------------------------------------------------------------------------

    def _on_sdo_read(self, index: int, subindex: int, **_) -> int | None:
        if index not in _ACTUAL_VALUES:
            return None
        with self._lock:
            return self._actual_values()[index]

    def _on_sdo_write(self, index: int, subindex: int, od: canopen.objectdictionary.ODVariable,
                      data: bytes) -> None:
        """Validate and act on SDO writes; LocalNode stores the bytes after this returns."""
        value = od.decode_raw(data)
        with self._lock:
            if _is_mapping(index):
                if self.node.nmt.state == "OPERATIONAL":
                    raise SdoAbortedError(SDO_ABORT_WRONG_STATE)
                if subindex > 0 and value != 0:
                    try:
                        pdo_layout.object_from_mapping_entry(value)
                    except ValueError:
                        raise SdoAbortedError(SDO_ABORT_NOT_MAPPABLE) from None
            if index == objects.CONTROLWORD:
                self._apply_controlword(value)
            elif index == objects.TARGET_CURRENT:
                self._target_current = value / objects.MILLI
            elif index == objects.TARGET_TORQUE:
                self._target_torque_permille = value
            elif index == objects.MODES_OF_OPERATION:
                if value not in _SUPPORTED_MODES:
                    raise SdoAbortedError(SDO_ABORT_VALUE_RANGE)
                self._mode = value
            elif index in _CONFIGURATION:
                self._config_dirty = True
            elif index == objects.FAULT_INJECTION:
                try:
                    fault = Fault(value)
                except ValueError:
                    raise SdoAbortedError(SDO_ABORT_VALUE_RANGE) from None
                self.inject(fault)

    # --- PDOs and SYNC ----------------------------------------------------------------------

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self._silent:
            return
        layout = self._rpdo_by_cob.get(can_id)
        if layout is None:
            return
        try:
            values = pdo_layout.decode(layout, bytes(data))
        except ValueError as exc:
            log.warning("node %d: %s", self.node_id, exc)
            return
        with self._lock:
            if objects.TARGET_CURRENT in values:
                self._target_current = values[objects.TARGET_CURRENT] / objects.MILLI
            if objects.TARGET_TORQUE in values:
                self._target_torque_permille = values[objects.TARGET_TORQUE]
            if objects.CONTROLWORD in values:
                self._apply_controlword(values[objects.CONTROLWORD])

    def _apply_controlword(self, controlword: int) -> None:
        command = cia402.command_from_controlword(controlword, self._controlword)
        self._controlword = controlword
        new_state = cia402.next_state(self.state, command)
        if self.state is State.FAULT and new_state is not State.FAULT:
            self.error_code = objects.EMCY_NO_ERROR
            self.node.emcy.reset()
        self.state = new_state

    def _commanded_current(self) -> float:
        if self.state is not State.OPERATION_ENABLED:
            return 0.0
        if self._mode == objects.MODE_CYCLIC_SYNC_CURRENT:
            return self._target_current
        if self._mode == objects.MODE_CYCLIC_SYNC_TORQUE:
            return self._target_torque_permille / objects.MILLI * self.rated_current
        return 0.0

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if self._silent or self.node.nmt.state != "OPERATIONAL":
            return
        with self._lock:
            self._sync_echo = data[0] if data else 0
            if self._config_dirty:
                self._read_configuration()
                self._config_dirty = False
            command = self._commanded_current()
            if abs(command) > self.trip_current:
                self._fault(objects.EMCY_OVERCURRENT, objects.ERROR_REGISTER_CURRENT)
                command = 0.0
            self.applied_current = max(-self.max_current, min(self.max_current, command))
            self.plant.advance(self.applied_current, self.period)
            self.sync_count += 1
            low, high = self.position_window
            if self.state is not State.FAULT and not low <= self.plant.position <= high:
                self._fault(objects.EMCY_POSITION_LIMIT, objects.ERROR_REGISTER_GENERIC)
            self._measurement = self.plant.measure()
            values = self._actual_values()
            due = self._pending_faults.pop(self.sync_count, None)
            if due is not None:
                self.inject(due)
                if self._silent or due is Fault.REBOOT:
                    return
            once, self._once = self._once, set()
            if Fault.ENCODER_GLITCH in once:
                values[objects.POSITION_ACTUAL] += ENCODER_JUMP
            if Fault.TORQUE_SENSOR_SATURATED in once:
                values[objects.JOINT_TORQUE_SENSOR] = SATURATED_READING
            frames = [(cob_id, pdo_layout.encode(layout, values)) for cob_id, layout in
                      self._tpdos]
        if Fault.TPDO_LATE in once:
            time.sleep(TPDO_DELAY)
        for cob_id, payload in frames * (2 if Fault.TPDO_TWICE in once else 1):
            self.network.send_message(cob_id, payload)

    def _fault(self, code: int, register: int) -> None:
        self.state = State.FAULT
        self.error_code = code
        self.applied_current = 0.0
        self.node.emcy.send(code, register)

    def _actual_values(self) -> dict[int, int]:
        m = self._measurement
        rated = self.rated_current
        return {
            objects.STATUSWORD: cia402.statusword_for(self.state),
            objects.POSITION_ACTUAL: m.position_increments,
            objects.VELOCITY_ACTUAL: m.velocity_increments_per_s,
            objects.MOTOR_CURRENT_ACTUAL: objects.amps_to_milliamps(m.motor_current),
            objects.JOINT_TORQUE_SENSOR: int(round(m.joint_torque_reading * objects.MILLI)),
            objects.CURRENT_ACTUAL: int(round(m.motor_current / rated * objects.MILLI)),
            objects.TORQUE_ACTUAL: int(round(m.motor_current / rated * objects.MILLI)),
            objects.MODES_OF_OPERATION_DISPLAY: self._mode,
            objects.ERROR_CODE: self.error_code,
            objects.SYNC_ECHO: self._sync_echo,
            objects.ERROR_REGISTER: (objects.ERROR_REGISTER_GENERIC
                                     if self.state is State.FAULT else 0),
        }


_SUPPORTED_MODES = (objects.MODE_NONE, objects.MODE_CYCLIC_SYNC_CURRENT,
                    objects.MODE_CYCLIC_SYNC_TORQUE)
_ACTUAL_VALUES = frozenset((
    objects.STATUSWORD, objects.POSITION_ACTUAL, objects.VELOCITY_ACTUAL,
    objects.MOTOR_CURRENT_ACTUAL, objects.JOINT_TORQUE_SENSOR, objects.CURRENT_ACTUAL,
    objects.TORQUE_ACTUAL, objects.MODES_OF_OPERATION_DISPLAY, objects.ERROR_CODE,
    objects.ERROR_REGISTER, objects.SYNC_ECHO))
_CONFIGURATION = (objects.MAX_CURRENT, objects.RATED_CURRENT, objects.OVERCURRENT_TRIP,
                  objects.CYCLE_PERIOD_US, objects.SOFTWARE_POSITION_LIMIT)


def _is_mapping(index: int) -> bool:
    return 0x1600 <= index < 0x1800 or 0x1A00 <= index < 0x1C00
