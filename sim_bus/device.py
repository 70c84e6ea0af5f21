"""A CiA 402 drive without a bus: its object values, its power state machine, its physics, its
faults and its reaction to a lost master. A fieldbus node exposes it: `sim_bus.canopen_node`
on CAN (SDO server, NMT, PDOs, SYNC), an EtherCAT slave with CoE and process data next. Both
call the same few methods, so the drive behaves the same whatever carries it:

    device = Cia402Device(model, payload, noise, eds_path=path)
    device.write(0x6040, 0, 0x0F)        # SDO / CoE download, or a received output PDO
    device.read(0x6064, 0)               # SDO / CoE upload, or a value to put in an input PDO
    device.cycle()                       # SYNC / the cycle's frame: latch, advance, sample
    device.master_lost("heartbeat")      # the bus noticed the master is gone

Time is the device's own: `cycle()` advances the physics exactly one communication cycle
period (0x1006), and nothing else does. The fault schedule counts these cycles.

Object values are integers in the dictionary's units; `read`/`write` validate as an SDO server
must and raise `DeviceAccessError` with the CiA 301 abort code, which a CANopen SDO server and a
CoE mailbox both send back as is.
"""

import functools
import logging
import math
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import NamedTuple

import numpy as np
from canopen.objectdictionary import datatypes

from model.parameters import ActuatorModel, Payload
from protocol import cia301, cia402, objects
from protocol import eds_path as shipped_eds_path
from protocol.cia402 import State
from protocol.dictionary import (
    default_value,
    integer_range,
    load_dictionary,
    mappable_object,
    variable,
)
from sim_bus import sensing
from sim_bus.faults import ENCODER_JUMP, Fault
from sim_bus.plant import Plant, SensorNoise

log = logging.getLogger(__name__)

# CiA 402 default of the quick stop option code 0x605A (slow down, then switch on disabled)
QUICK_STOP_OPTION_DEFAULT = 2
# the choice for a drive whose EDS has no 0x6007: a lost master means quick stop
ABORT_CONNECTION_DEFAULT = objects.ABORT_QUICK_STOP
DEFAULT_PERIOD = 1e-3  # s: the elbow's 1 kHz, while 0x1006 is 0 (not configured yet)

# what the drive's hardware fixes (its encoder, its motor's ratings): where an EDS gives no
# default for these, the virtual drive answers its own hardware's values (those of the shipped
# elbow drive's EDS), as a real drive answers what it is, not 0
_HARDWARE_OBJECTS = ((objects.ENCODER_RESOLUTION, 1), (objects.ENCODER_RESOLUTION, 2),
                     (objects.RATED_CURRENT, 0), (objects.RATED_TORQUE, 0))

EmergencyHandler = Callable[[int, int], None]  # (error code, error register)
FaultHandler = Callable[[Fault], None]

# Faults the device acts out itself; the others are the exposing node's (see `inject`)
_DEVICE_FAULTS = frozenset((Fault.ENCODER_GLITCH, Fault.TORQUE_SENSOR_SATURATED,
                            Fault.OVERCURRENT_TRIP))
_POWERED = frozenset((State.SWITCHED_ON, State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE))
# quick stop option codes 1..4 end in switch on disabled once the motor stands still
_QUICK_STOP_ENDS_DISABLED = range(1, 5)
# keys of the objects every cycle writes (built once, not per cycle)
_SYNC_ECHO = (objects.SYNC_ECHO, 0)
_POSITION_ACTUAL = (objects.POSITION_ACTUAL, 0)
_JOINT_TORQUE_SENSOR = (objects.JOINT_TORQUE_SENSOR, 0)
_STATUSWORD = (objects.STATUSWORD, 0)
_VELOCITY_ACTUAL = (objects.VELOCITY_ACTUAL, 0)
_MOTOR_CURRENT_ACTUAL = (objects.MOTOR_CURRENT_ACTUAL, 0)
_CURRENT_ACTUAL = (objects.CURRENT_ACTUAL, 0)
_TORQUE_ACTUAL = (objects.TORQUE_ACTUAL, 0)
_CONTROLWORD = (objects.CONTROLWORD, 0)
_TARGET_TORQUE = (objects.TARGET_TORQUE, 0)
_TARGET_CURRENT = (objects.TARGET_CURRENT, 0)
_STATUSWORDS = {state: cia402.statusword_for(state) for state in State}
# a line's batch (`line_terms`): what the command is, the readings each cycle samples (in
# this order) and the objects it writes back, echo and statusword first
COMMAND_NONE, COMMAND_CURRENT, COMMAND_TORQUE = range(3)
NEVER = 1 << 62  # the cycle of a fault that is not scheduled
LIVE_READINGS = (_POSITION_ACTUAL, _VELOCITY_ACTUAL, _MOTOR_CURRENT_ACTUAL,
                 _JOINT_TORQUE_SENSOR, _CURRENT_ACTUAL, _TORQUE_ACTUAL)
LINE_KEYS = (_SYNC_ECHO, _STATUSWORD) + LIVE_READINGS


class LineTerms(NamedTuple):
    """A drive's terms for a line's batch (`Cia402Device.line_terms`)."""

    steady: bool  # no quick stop to finish, no sensor fault pending
    commanded: bool  # the state is the one the controlword led to (a repeat does nothing)
    controlword: int
    kind: int  # COMMAND_*: what the target means in this state and mode
    braked: bool
    faulted: bool  # in FAULT: the position window is not watched
    statusword: int
    next_due: int  # cycle of the next scheduled fault
    cycle_count: int
    period: float  # s
    max_current: float  # A
    trip_current: float  # A
    window: tuple[float, float]  # rad
    increments_per_rad: float
    rated_current: float  # A
    rated_torque: float  # N.m
    drive_gain: float  # N.m/A
    target_current: float  # A
    target_torque_permille: int
    ranges: tuple  # (low, high) of each LIVE_READINGS object
    readings: tuple  # each LIVE_READINGS object's value now
_WRITABLE = frozenset(("rw", "wo", "rww", "rwr"))
_READABLE = frozenset(("rw", "ro", "const", "rww", "rwr"))


def _value_range(dictionary, key: tuple[int, int]) -> tuple[int, int]:
    """The integer range an object holds (its DataType's); int64's without the object."""
    var = variable(dictionary, *key)
    if var is None or var.data_type not in datatypes.INTEGER_TYPES:
        return -(1 << 63), (1 << 63) - 1
    return integer_range(var)


@functools.cache
def hardware_values() -> dict[tuple[int, int], int]:
    """The virtual drive's own hardware values (`_HARDWARE_OBJECTS` in the shipped EDS)."""
    shipped = load_dictionary(shipped_eds_path())
    return {key: default_value(variable(shipped, *key)) for key in _HARDWARE_OBJECTS}


def power_on_value(var) -> int | str | bytes:
    """What an object holds after a reset: the EDS's default, else for a hardware object the
    drive's own value, else 0."""
    if var.value is None and var.default is None:
        return hardware_values().get((var.index, var.subindex), 0)
    return default_value(var)


class DeviceAccessError(Exception):
    """A refused object access; `abort_code` is the CiA 301 SDO abort code to send back."""

    def __init__(self, abort_code: int, message: str):
        super().__init__(message)
        self.abort_code = abort_code


class Cia402Device:
    """A CiA 402 torque drive for one joint, its physics from the actuator model.

    Modes: 10 cyclic synchronous torque (0x6071, per mille of rated torque 0x6076, converted to
    motor current with the model's drive gain) and, where the EDS has 0x2000, -1 cyclic
    synchronous current (manufacturer specific, mA). The command is saturated at max current
    0x6073; above the trip level 0x2003 (where the EDS has it) the drive faults (EMCY 0x2310),
    as it does leaving the software position window 0x607D (EMCY 0x8612). The holding brake
    is engaged whenever the state is not operation enabled.

    `node_id` only resolves `$NODEID` defaults of the EDS (CANopen COB-IDs).
    """

    def __init__(self, model: ActuatorModel, payload: Payload = Payload(),
                 noise: SensorNoise = SensorNoise(), *, eds_path: str | Path | None = None,
                 initial_position: float | None = None, node_id: int | None = None):
        self.model = model
        self.eds_path = Path(eds_path) if eds_path is not None else shipped_eds_path()
        self.dictionary = load_dictionary(self.eds_path, node_id)
        self._reading_range = {key: _value_range(self.dictionary, key)
                               for key in LIVE_READINGS}
        # what the compiled period (`sim_bus.sensing`) reads and writes, made once: the
        # drive's terms (from `_configure` and the plant's parameters), the readings' ranges,
        # the readings of the last sample
        self._terms = np.zeros(sensing.N_TERMS)
        self._ranges = np.array([self._reading_range[key] for key in LIVE_READINGS],
                                dtype=np.int64)
        self._readings = np.zeros(sensing.N_READINGS, dtype=np.int64)
        self._terms_of_plant = -1  # the plant's revision the terms hold
        self._variables = {}
        for obj in self.dictionary.values():
            for var in (obj.values() if hasattr(obj, "values") else (obj,)):
                self._variables[(var.index, var.subindex)] = var
        self.plant = Plant(model.parameters, payload, noise, initial_position)
        self.plant.warm_up()
        self._lock = threading.RLock()
        self._emergency_handlers: list[EmergencyHandler] = []
        self._fault_handlers: list[FaultHandler] = []
        self._schedule: list[tuple[int, Fault]] = []  # (cycle, fault), due when cycle is reached
        self._once: set[Fault] = set()  # faults that act on the next sample
        self.injected: list[tuple[int, Fault]] = []  # (cycle, fault) as they happened
        self._cycle_count = 0
        self._applied_current = 0.0
        # a line whose batch may hold this drive's latest cycles (`sim_bus.line_physics`):
        # they are written back here before anything reads or changes the drive
        self._line = None
        # counts every change a line's batch (`sim_bus.line_physics`) derives its terms from:
        # state, configuration, an object written, a fault scheduled or injected
        self.revision = 0
        self.master_loss: str | None = None  # why the master was declared lost, until reset
        self._alone: tuple[float, int] | None = None  # see `run_alone`
        self._values: dict[tuple[int, int], int] = {}
        self._stored: dict[tuple[int, int], int] = {}  # see `store`
        self.reset_application()

    # --- handlers the exposing node registers -----------------------------------------------

    def add_emergency_handler(self, handler: EmergencyHandler) -> None:
        """`handler(code, register)` for each emergency (code 0: error reset), to be sent as
        EMCY on CAN or as a CoE emergency on EtherCAT."""
        self._emergency_handlers.append(handler)

    def add_fault_handler(self, handler: FaultHandler) -> None:
        """`handler(fault)` for injected faults of the communication (silent, heartbeat stops,
        late or doubled frames, flood, reboot): the node acts them out. Called from within
        `cycle()` for scheduled faults, so the node can change that cycle's answer."""
        self._fault_handlers.append(handler)

    # --- state ------------------------------------------------------------------------------

    @property
    def period(self) -> float:
        """s, the communication cycle period 0x1006 (1 ms while unconfigured)."""
        return self._period

    @property
    def state(self) -> State:
        return self._state

    @property
    def brake_engaged(self) -> bool:
        return self._state is not State.OPERATION_ENABLED

    @property
    def power_stage_on(self) -> bool:
        return self._state in _POWERED

    @property
    def at_rest(self) -> bool:
        """Power stage off and the joint standing still: nothing changes without a master."""
        return self._state not in _POWERED and self.plant.velocity == 0.0

    @property
    def cycle_count(self) -> int:
        """Cycles run since power-on."""
        self._settle()
        return self._cycle_count

    @property
    def applied_current(self) -> float:
        """A, the current the last cycle applied."""
        self._settle()
        return self._applied_current

    @applied_current.setter
    def applied_current(self, current: float) -> None:
        self._applied_current = current

    def _changed(self) -> None:
        """Something a line's batch derives its terms from changed (see `revision`)."""
        self.revision += 1
        if self._line is not None:
            self._line.changed = True

    def join_line(self, line) -> None:
        """`line` (a `sim_bus.line_physics.DriveLine`) may run this drive's cycles from now on;
        its plant lives in the line's rows."""
        self._line = line
        self.plant.on_change = lambda: setattr(line, "changed", True)

    def _settle(self) -> None:
        """The cycles a line's batch ran for this drive, written back (see `_line`)."""
        line = self._line
        if line is not None and line.pending:
            line.flush()

    def _set_state(self, state: State) -> None:
        self._changed()
        self._state = state
        self._statusword = _STATUSWORDS[state]  # sampled every cycle, changes with the state

    # --- resets -----------------------------------------------------------------------------

    def reset_application(self) -> None:
        """Power-on values for every object, power stage off (CANopen NMT reset node)."""
        self._settle()
        with self._lock:
            for key, var in self._variables.items():
                self._values[key] = power_on_value(var)
            self._values.update(self._stored)
            self._after_reset()
            self.master_loss = None

    def store(self, values: dict[tuple[int, int], int]) -> None:
        """Write these objects (checked as SDO writes) and keep them over power-on resets, as
        a drive keeps what a commissioning tool stored in its non-volatile memory (CiA 301
        0x1010): the joint-specific settings of `sim_bus.commissioning`. Objects the
        dictionary lacks are skipped."""
        with self._lock:
            for (index, subindex), value in values.items():
                if (index, subindex) in self._variables:
                    self.write(index, subindex, value)
                    self._stored[(index, subindex)] = value

    def reset_communication(self) -> None:
        """Power-on values for the communication objects (0x1000..0x1FFF). The power stage
        goes off too: a master that resets the drive never inherits it enabled."""
        self._settle()
        with self._lock:
            for key, var in self._variables.items():
                if key[0] < 0x2000:
                    self._values[key] = power_on_value(var)
            self._after_reset()
            self.master_loss = None

    def _after_reset(self) -> None:
        self._controlword = 0
        self._commanded_state: State | None = None  # what the controlword last led to
        self._target_current = 0.0
        self._target_torque_permille = 0
        self.applied_current = 0.0
        self._error(cia301.EMCY_NO_ERROR, 0)
        self._set_state(State.SWITCH_ON_DISABLED)
        self._configure()
        self._mode = self._values.get((objects.MODES_OF_OPERATION, 0), objects.MODE_NONE)
        self._values[(objects.MODES_OF_OPERATION_DISPLAY, 0)] = self._mode
        self.plant.sample(self._sensing_terms(), self._ranges, self._readings)
        self._sample()

    def _configure(self) -> None:
        """Cache what the cycle needs from the dictionary (after a reset or a write to it)."""
        self._changed()
        v = self._values
        self.rated_current = v.get((objects.RATED_CURRENT, 0), 0) / objects.MILLI  # A
        self.rated_torque = v.get((objects.RATED_TORQUE, 0), 0) / objects.MILLI  # N.m
        max_permille = v.get((objects.MAX_CURRENT, 0))
        self.max_current = (max_permille / objects.MILLI * self.rated_current
                            if max_permille is not None else self.model.limits.current_max)
        trip = v.get((objects.OVERCURRENT_TRIP, 0))
        self.trip_current = trip / objects.MILLI if trip is not None else float("inf")
        period_us = v.get((objects.CYCLE_PERIOD_US, 0), 0)
        self._period = period_us * 1e-6 if period_us > 0 else DEFAULT_PERIOD
        increments = v.get((objects.ENCODER_RESOLUTION, 1), 0)
        revolutions = v.get((objects.ENCODER_RESOLUTION, 2), 0)
        self.increments_per_rad = (increments / revolutions / (2.0 * math.pi)
                                   if increments > 0 and revolutions > 0
                                   else objects.INCREMENTS_PER_RAD)
        low = v.get((objects.SOFTWARE_POSITION_LIMIT, 1))
        high = v.get((objects.SOFTWARE_POSITION_LIMIT, 2))
        self.position_window = (
            low / self.increments_per_rad if low is not None else float("-inf"),
            high / self.increments_per_rad if high is not None else float("inf"))
        self.drive_gain = self.model.parameters.drive_gain
        # the readings a drive without a rating leaves as they are (see `sensing`)
        self._readings[4] = v.get(_CURRENT_ACTUAL, 0)
        self._readings[5] = v.get(_TORQUE_ACTUAL, 0)
        self._terms_of_plant = -1

    def _sensing_terms(self) -> np.ndarray:
        """The terms of the compiled period, read again when the configuration or the
        plant's parameters changed."""
        plant = self.plant
        if self._terms_of_plant != plant.revision:
            self._terms_of_plant = plant.revision
            t = self._terms
            t[sensing.T_PERIOD] = self._period
            t[sensing.T_PER_RAD] = self.increments_per_rad
            t[sensing.T_RATED_CURRENT] = self.rated_current
            t[sensing.T_RATED_TORQUE] = self.rated_torque
            t[sensing.T_DRIVE_GAIN] = self.drive_gain
            t[sensing.T_SENSOR_GAIN] = plant.parameters.torque_sensor_gain
            t[sensing.T_NOISE_CURRENT] = plant.noise.current
            t[sensing.T_NOISE_TORQUE] = plant.noise.joint_torque
        return self._terms

    # --- object access ----------------------------------------------------------------------

    def _variable(self, index: int, subindex: int):
        var = self._variables.get((index, subindex))
        if var is None:
            if index in self.dictionary:
                raise DeviceAccessError(cia301.SDO_ABORT_NO_SUBINDEX,
                                        f"0x{index:04X} has no sub-index {subindex}")
            raise DeviceAccessError(cia301.SDO_ABORT_NOT_IN_DICTIONARY,
                                    f"0x{index:04X} is not in the dictionary")
        return var

    def read(self, index: int, subindex: int = 0) -> int:
        """The object's value (live objects as of the last cycle or state change)."""
        self._settle()
        var = self._variable(index, subindex)
        if var.access_type not in _READABLE:
            raise DeviceAccessError(cia301.SDO_ABORT_READ_WRITE_ONLY,
                                    f"0x{index:04X}:{subindex:02X} is write-only")
        if index == objects.STATUSWORD:
            return cia402.statusword_for(self._state)  # acyclic reads see the state now
        return self._values[(index, subindex)]

    def read_bytes(self, index: int, subindex: int = 0) -> bytes:
        """`read`, encoded as the object's data type (what an SDO upload carries)."""
        value = self.read(index, subindex)
        return self._variables[(index, subindex)].encode_raw(value)

    def write_bytes(self, index: int, subindex: int, data: bytes) -> None:
        """`write` from an SDO download's bytes (length checked against the data type)."""
        self._settle()
        var = self._variable(index, subindex)
        if isinstance(self._values[(index, subindex)], int) and len(data) * 8 != len(var):
            raise DeviceAccessError(cia301.SDO_ABORT_LENGTH_MISMATCH,
                                    f"0x{index:04X}:{subindex:02X} takes {len(var) // 8} "
                                    f"bytes, not {len(data)}")
        value = var.decode_raw(bytes(data))
        if not isinstance(value, int):
            self._check_writable(var)
            self._values[(index, subindex)] = value
            return
        self.write(index, subindex, value)

    def write(self, index: int, subindex: int, value: int) -> None:
        """Validate and act on a write (controlword, mode, targets, configuration, fault
        injection); DeviceAccessError with the abort code when refused."""
        self._settle()
        var = self._variable(index, subindex)
        self._check_writable(var)
        bits = len(var)
        signed = var.data_type in cia301.SIGNED_TYPES
        low, high = (-(1 << bits - 1), (1 << bits - 1) - 1) if signed else (0, (1 << bits) - 1)
        if var.min is not None:
            low = max(low, var.min)
        if var.max is not None:
            high = min(high, var.max)
        if value < low:
            raise DeviceAccessError(cia301.SDO_ABORT_VALUE_TOO_LOW,
                                    f"0x{index:04X}:{subindex:02X}: {value} < {low}")
        if value > high:
            raise DeviceAccessError(cia301.SDO_ABORT_VALUE_TOO_HIGH,
                                    f"0x{index:04X}:{subindex:02X}: {value} > {high}")
        with self._lock:
            self._act(index, subindex, value)

    def _check_writable(self, var) -> None:
        if var.access_type not in _WRITABLE:
            raise DeviceAccessError(cia301.SDO_ABORT_WRITE_READ_ONLY,
                                    f"0x{var.index:04X}:{var.subindex:02X} is read-only")

    def _act(self, index: int, subindex: int, value: int) -> None:
        self._changed()
        if index == objects.CONTROLWORD:
            self._apply_controlword(value)
        elif index == objects.TARGET_CURRENT:
            self._target_current = value / objects.MILLI
        elif index == objects.TARGET_TORQUE:
            self._target_torque_permille = value
        elif index == objects.MODES_OF_OPERATION:
            if value not in self.supported_modes():
                raise DeviceAccessError(cia301.SDO_ABORT_VALUE_RANGE,
                                        f"mode of operation {value} not supported")
            self._mode = value
            self._values[(objects.MODES_OF_OPERATION_DISPLAY, 0)] = value
        elif index == objects.FAULT_INJECTION:
            try:
                fault = Fault(value)
            except ValueError:
                raise DeviceAccessError(cia301.SDO_ABORT_VALUE_RANGE,
                                        f"no fault with code {value}") from None
            self.inject(fault)
        elif objects.is_pdo_mapping(index) and subindex > 0 and value != 0:
            try:
                mappable_object(self.dictionary, value)
            except ValueError as exc:
                raise DeviceAccessError(cia301.SDO_ABORT_NOT_MAPPABLE, str(exc)) from None
        elif objects.is_pdo_mapping(index) and subindex == 0:
            entries = len(self.dictionary[index]) - 1
            if value > entries:
                raise DeviceAccessError(cia301.SDO_ABORT_PDO_LENGTH,
                                        f"0x{index:04X} has {entries} entries, not {value}")
        self._values[(index, subindex)] = value
        if index in _CONFIGURATION:
            self._configure()

    def supported_modes(self) -> tuple[int, ...]:
        """Modes this drive acts out: the torque modes its dictionary has targets for."""
        modes = [objects.MODE_NONE]
        if (objects.TARGET_TORQUE, 0) in self._variables:
            modes.append(objects.MODE_CYCLIC_SYNC_TORQUE)
        if (objects.TARGET_CURRENT, 0) in self._variables:
            modes.append(objects.MODE_CYCLIC_SYNC_CURRENT)
        return tuple(modes)

    def write_outputs(self, keys: tuple[tuple[int, int], ...], values: tuple[int, ...]) -> None:
        """Act on a received output PDO's values (already in their types' ranges: the PDO
        codec made them), without the per-object checks of an SDO write. A master repeats
        its controlword and, holding, its target every cycle: a value the drive holds and
        has acted on already changes nothing, and is passed over."""
        if self._line is not None:
            self._settle()
        with self._lock:
            v = self._values
            for key, value in zip(keys, values, strict=True):
                if v.get(key) == value and self._acted_on(key, value):
                    continue
                self._act(key[0], key[1], value)

    def _acted_on(self, key: tuple[int, int], value: int) -> bool:
        """Whether `value` of the output `key` (the value it holds) is in force: writing it
        again would change nothing (`_act`, `_apply_controlword`)."""
        if key == _CONTROLWORD:
            return value == self._controlword and self._state is self._commanded_state
        if key == _TARGET_TORQUE:
            return value == self._target_torque_permille
        if key == _TARGET_CURRENT:
            return value / objects.MILLI == self._target_current
        return False

    def setting(self, key: tuple[int, int]) -> int:
        """The value of a setting (an object no cycle writes: neither a line's batch,
        `LINE_KEYS` and the outputs, nor the sample), as `values[key]` without settling a
        line's batch: what a bus node checks every frame (0x1019 at each SYNC)."""
        return self._values[key]

    @property
    def values(self) -> Mapping[tuple[int, int], int]:
        """Every object's value by (index, subindex), live objects as sampled by the last
        cycle: what an input PDO carries (read-only; `read` for checked access)."""
        self._settle()
        return self._values

    # --- CiA 402 ----------------------------------------------------------------------------

    def _apply_controlword(self, controlword: int) -> None:
        if controlword == self._controlword and self._state is self._commanded_state:
            # the master repeats its controlword every cycle: no rising edge (no fault reset),
            # and a command applied again to the state it led to leaves it there
            # (cia402.next_state is idempotent), so the state machine has nothing to do
            return
        command = cia402.command_from_controlword(controlword, self._controlword)
        self._controlword = controlword
        new_state = cia402.next_state(self._state, command)
        if self._state is State.FAULT and new_state is not State.FAULT:
            self._error(cia301.EMCY_NO_ERROR, 0)
            self._emit(cia301.EMCY_NO_ERROR, 0)
        self._set_state(new_state)
        self._commanded_state = new_state

    def _commanded_current(self) -> float:
        if self._state is not State.OPERATION_ENABLED:
            return 0.0
        if self._mode == objects.MODE_CYCLIC_SYNC_CURRENT:
            return self._target_current
        if self._mode == objects.MODE_CYCLIC_SYNC_TORQUE:
            return self._target_torque_permille / objects.MILLI * self.rated_torque / (
                self.drive_gain)
        return 0.0

    def _fault(self, code: int, register: int) -> None:
        """Fault reaction: power stage off (the brake engages), error code, emergency."""
        self._set_state(State.FAULT)
        self.applied_current = 0.0
        self._error(code, register)
        self._emit(code, register)

    def _error(self, code: int, register: int) -> None:
        self._values[(objects.ERROR_CODE, 0)] = code
        self._values[(objects.ERROR_REGISTER, 0)] = register | (
            cia301.ERROR_REGISTER_GENERIC if code else 0)

    def _emit(self, code: int, register: int) -> None:
        for handler in self._emergency_handlers:
            handler(code, register)

    def master_lost(self, reason: str, code: int = cia301.EMCY_HEARTBEAT) -> None:
        """The bus declared the master gone (consumer heartbeat timeout, SYNC/RPDO silence,
        an EtherCAT watchdog): emergency `code`, then the abort connection reaction 0x6007
        (quick stop by default). Once per loss: a reset re-arms it."""
        self._settle()
        with self._lock:
            if self.master_loss is not None:
                return
            self.master_loss = reason
            log.warning("master lost: %s", reason)
            option = self._values.get((objects.ABORT_CONNECTION_OPTION, 0),
                                      ABORT_CONNECTION_DEFAULT)
            if option == objects.ABORT_FAULT and self._state is not State.FAULT:
                self._fault(code, cia301.ERROR_REGISTER_COMMUNICATION)
                return
            self._error(code, cia301.ERROR_REGISTER_COMMUNICATION)
            self._emit(code, cia301.ERROR_REGISTER_COMMUNICATION)
            if option == objects.ABORT_DISABLE_VOLTAGE:
                self._set_state(cia402.next_state(self._state, cia402.Command.DISABLE_VOLTAGE))
            elif option == objects.ABORT_QUICK_STOP:
                self._set_state(cia402.next_state(self._state, cia402.Command.QUICK_STOP))
                self._finish_quick_stop()

    def master_found(self) -> None:
        """A master started cyclic exchange with the drive (EtherCAT: PRE-OP -> SAFE-OP):
        its loss will be reacted to again. On CAN the NMT reset that every master starts with
        does this. Without it a drive reacts to the first master it loses only, and a later
        master's death leaves it enabled."""
        with self._lock:
            self.master_loss = None
            self._alone = None

    def run_alone(self, now: float) -> None:
        """From the exposing node's watch (`now`: the drive's own time, s): a drive whose
        master is gone keeps its own control loop running, one cycle a period, so its quick
        stop ends in switch on disabled once the motor stands still and a loaded joint moves
        as it would, without anyone sending a SYNC or a frame. Cycles the bus drives (a new
        master's) take precedence: while they come nothing runs here, so on lock-step drive
        time, which only the bus's cycles advance, nothing ever does."""
        self._settle()
        if self.master_loss is None and self._alone is None:
            return  # the every-frame case, without the lock
        with self._lock:
            if self.master_loss is None or self.at_rest:
                self._alone = None
                return
            if self._alone is None or self._alone[1] != self.cycle_count:
                self._alone = (now, self.cycle_count)  # from here on, or the bus cycled it
                return
            since = self._alone[0]
            cycles = int((now - since) / self._period)
            for _ in range(cycles):
                self.cycle(self._values[_SYNC_ECHO])
                if self.at_rest:
                    break
            self._alone = (since + cycles * self._period, self.cycle_count)

    def _finish_quick_stop(self) -> None:
        """Quick stop in a torque drive: no torque, brake engaged; once the joint stands
        still the drive goes on to switch on disabled (option codes 1..4, 0x605A)."""
        if self._state is not State.QUICK_STOP_ACTIVE or self.plant.velocity != 0.0:
            return
        option = self._values.get((objects.QUICK_STOP_OPTION, 0), QUICK_STOP_OPTION_DEFAULT)
        if option in _QUICK_STOP_ENDS_DISABLED:
            self._set_state(State.SWITCH_ON_DISABLED)

    # --- the cycle --------------------------------------------------------------------------

    def cycle(self, counter: int = 0) -> None:
        """One communication cycle: latch the command, advance the physics one period, sample
        the sensors, fire the faults due. `counter` is the cycle's number as the bus gives it
        (the SYNC counter byte), echoed in 0x2004 where the drive has it."""
        if self._line is not None:
            self._settle()
        with self._lock:
            self._values[_SYNC_ECHO] = counter
            command = self._commanded_current()
            if abs(command) > self.trip_current:
                self._fault(cia301.EMCY_OVERCURRENT, cia301.ERROR_REGISTER_CURRENT)
                command = 0.0
            limit = self.max_current
            self._applied_current = applied = -limit if command < -limit else (
                limit if command > limit else command)
            # the readings are of the plant at the period's end, whatever the checks below
            # make of the drive's state (a fault shows in the next sample's statusword)
            position = self.plant.advance_sampled(
                applied, self._state is not State.OPERATION_ENABLED, self._sensing_terms(),
                self._ranges, self._readings)
            self._cycle_count += 1
            low, high = self.position_window
            if self._state is not State.FAULT and not low <= position <= high:
                self._fault(cia301.EMCY_POSITION_LIMIT, cia301.ERROR_REGISTER_GENERIC)
            self._finish_quick_stop()
            self._sample()
            while self._schedule and self._schedule[0][0] <= self._cycle_count:
                self.inject(self._schedule.pop(0)[1])
            if self._once:
                once, self._once = self._once, set()
                if Fault.ENCODER_GLITCH in once:
                    self._values[_POSITION_ACTUAL] += ENCODER_JUMP
                if Fault.TORQUE_SENSOR_SATURATED in once:
                    self._values[_JOINT_TORQUE_SENSOR] = cia301.INT32_MAX

    # --- a line's batch (sim_bus.line_physics) ----------------------------------------------

    def line_terms(self) -> "LineTerms":
        """What a line's batch needs to run this drive's next cycles in its place, as of now
        (valid until `revision` changes): the cycle of `cycle()` without its events. The
        batch leaves a cycle to `cycle()` when the controlword would act, the command would
        trip, the joint leaves its window, a quick stop is to finish, or a fault is due."""
        self._settle()
        state = self._state
        if state is not State.OPERATION_ENABLED or self._mode not in (
                objects.MODE_CYCLIC_SYNC_CURRENT, objects.MODE_CYCLIC_SYNC_TORQUE):
            kind = COMMAND_NONE
        else:
            kind = (COMMAND_CURRENT if self._mode == objects.MODE_CYCLIC_SYNC_CURRENT
                    else COMMAND_TORQUE)
        r = self._reading_range
        v = self._values
        return LineTerms(
            steady=state is not State.QUICK_STOP_ACTIVE and not self._once,
            commanded=state is self._commanded_state, controlword=self._controlword,
            kind=kind, braked=self.brake_engaged, faulted=state is State.FAULT,
            statusword=self._statusword,
            next_due=self._schedule[0][0] if self._schedule else NEVER,
            cycle_count=self._cycle_count, period=self._period, max_current=self.max_current,
            trip_current=self.trip_current, window=self.position_window,
            increments_per_rad=self.increments_per_rad, rated_current=self.rated_current,
            rated_torque=self.rated_torque, drive_gain=self.drive_gain,
            target_current=self._target_current,
            target_torque_permille=self._target_torque_permille,
            ranges=tuple(r[key] for key in LIVE_READINGS),
            readings=tuple(v.get(key, 0) for key in LIVE_READINGS))

    def cycled_by_line(self, keys: tuple, values: list, cycle_count: int,
                       applied_current: float, target_current: float,
                       target_torque_permille: int) -> None:
        """A line's batch ran this drive's cycles up to `cycle_count`: its objects `keys`
        (`LINE_KEYS` and the outputs it took) hold `values`, as `cycle()` would have left
        them."""
        self._values.update(zip(keys, values, strict=True))
        self._cycle_count = cycle_count
        self._applied_current = applied_current
        self._target_current = target_current
        self._target_torque_permille = target_torque_permille

    def _sample(self) -> None:
        """The last sensors' reading (`_readings`, the compiled period's) and the statusword,
        latched into the objects an input process data carries: a fault due later in the
        same cycle shows in the next sample (its emergency goes out at once)."""
        v = self._values
        v[_STATUSWORD] = self._statusword
        v.update(zip(LIVE_READINGS, self._readings.tolist(), strict=True))

    # --- faults -----------------------------------------------------------------------------

    def schedule(self, fault: Fault, seconds: float) -> None:
        """Inject `fault` when the drive's time (cycles x period) reaches `seconds`; a time of
        0 fires at the first cycle, and several faults due in one cycle all fire."""
        with self._lock:
            self._changed()
            self._schedule.append((int(round(seconds / self._period)), fault))
            self._schedule.sort(key=lambda item: item[0])

    def inject(self, fault: Fault) -> None:
        """Inject `fault` now: the device acts out its own (sensor glitches on the next
        sample, over-current trip), the fault handlers the communication's."""
        self._settle()
        with self._lock:
            self._changed()
            self.injected.append((self.cycle_count, fault))
            if fault is Fault.OVERCURRENT_TRIP:
                self._fault(cia301.EMCY_OVERCURRENT, cia301.ERROR_REGISTER_CURRENT)
            elif fault in _DEVICE_FAULTS:
                self._once.add(fault)
            elif fault is not Fault.NONE:
                if not self._fault_handlers:
                    log.warning("fault %s: no bus node to act it out", fault.name.lower())
                for handler in self._fault_handlers:
                    handler(fault)


_CONFIGURATION = frozenset((
    objects.MAX_CURRENT, objects.RATED_CURRENT, objects.RATED_TORQUE, objects.OVERCURRENT_TRIP,
    objects.CYCLE_PERIOD_US, objects.SOFTWARE_POSITION_LIMIT, objects.ENCODER_RESOLUTION))

