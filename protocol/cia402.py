"""CiA 402 power state machine as pure functions, shared by the drive (decode controlword,
next state) and the master (decode statusword, next controlword toward a goal)."""

import functools
from enum import Enum


class State(Enum):
    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"


class Command(Enum):
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    DISABLE_OPERATION = 0x0007
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


# (mask, value, state), CiA 402 table "statusword bits for the state".
_STATUSWORD_PATTERNS = (
    (0x004F, 0x0000, State.NOT_READY_TO_SWITCH_ON),
    (0x004F, 0x0040, State.SWITCH_ON_DISABLED),
    (0x006F, 0x0021, State.READY_TO_SWITCH_ON),
    (0x006F, 0x0023, State.SWITCHED_ON),
    (0x006F, 0x0027, State.OPERATION_ENABLED),
    (0x006F, 0x0007, State.QUICK_STOP_ACTIVE),
    (0x004F, 0x000F, State.FAULT_REACTION_ACTIVE),
    (0x004F, 0x0008, State.FAULT),
)

# operation enabled, the one state a running cycle accepts (its row of the table above), for
# checks over many statuswords at once
OPERATION_ENABLED_MASK, OPERATION_ENABLED_BITS = 0x006F, 0x0027

_STATE_BITS = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0021,
    State.SWITCHED_ON: 0x0023,
    State.OPERATION_ENABLED: 0x0027,
    State.QUICK_STOP_ACTIVE: 0x0007,
    State.FAULT_REACTION_ACTIVE: 0x000F,
    State.FAULT: 0x0008,
}

STATUSWORD_VOLTAGE_ENABLED = 0x0010
STATUSWORD_REMOTE = 0x0200
STATUSWORD_INTERNAL_LIMIT = 0x0800
CONTROLWORD_FAULT_RESET_BIT = 0x0080


@functools.cache  # a master decodes every sample's statusword; a drive reports a handful
def state_from_statusword(statusword: int) -> State:
    for mask, value, state in _STATUSWORD_PATTERNS:
        if statusword & mask == value:
            return state
    raise ValueError(f"statusword 0x{statusword:04X} matches no CiA 402 state")


def statusword_for(state: State, internal_limit: bool = False) -> int:
    """The statusword a drive in `state` reports (remote bit set; voltage enabled when powered)."""
    word = _STATE_BITS[state] | STATUSWORD_REMOTE
    if state not in (State.NOT_READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED):
        word |= STATUSWORD_VOLTAGE_ENABLED
    if internal_limit:
        word |= STATUSWORD_INTERNAL_LIMIT
    return word


def command_from_controlword(controlword: int, previous: int) -> Command | None:
    """Decode a controlword (CiA 402 table 'device control commands'); fault reset is the
    rising edge of bit 7, so the previous controlword is needed."""
    if controlword & CONTROLWORD_FAULT_RESET_BIT:
        if not previous & CONTROLWORD_FAULT_RESET_BIT:
            return Command.FAULT_RESET
        return None
    low = controlword & 0x000F
    if not low & 0x0002:
        return Command.DISABLE_VOLTAGE
    if low & 0x0006 == 0x0002:
        return Command.QUICK_STOP
    if low & 0x0007 == 0x0006:
        return Command.SHUTDOWN
    if low == 0x0007:
        return Command.SWITCH_ON
    if low == 0x000F:
        return Command.ENABLE_OPERATION
    return None


def next_state(state: State, command: Command | None) -> State:
    """Drive-side transition for a decoded command; unknown or inapplicable commands keep the
    state, as a real drive does."""
    if command is None:
        return state
    if state is State.FAULT:
        return State.SWITCH_ON_DISABLED if command is Command.FAULT_RESET else state
    if state in (State.FAULT_REACTION_ACTIVE, State.NOT_READY_TO_SWITCH_ON):
        return state
    if command is Command.DISABLE_VOLTAGE:
        return State.SWITCH_ON_DISABLED
    if command is Command.QUICK_STOP:
        if state is State.OPERATION_ENABLED or state is State.QUICK_STOP_ACTIVE:
            # held, the quick stop runs on: it ends in switch on disabled when the motor
            # stands still (option 0x605A) or on disable voltage, not on its own repetition
            return State.QUICK_STOP_ACTIVE
        return State.SWITCH_ON_DISABLED
    if state is State.QUICK_STOP_ACTIVE:
        return state
    if command is Command.SHUTDOWN:
        return State.READY_TO_SWITCH_ON
    if command is Command.SWITCH_ON:
        if state in (State.READY_TO_SWITCH_ON, State.OPERATION_ENABLED):
            return State.SWITCHED_ON
        return state
    if command is Command.ENABLE_OPERATION:
        if state in (State.SWITCHED_ON, State.READY_TO_SWITCH_ON):
            return State.OPERATION_ENABLED
        return state
    return state


def controlword_toward(state: State, goal: State) -> int | None:
    """Master side: the next controlword on the path from `state` to `goal` (one of switch on
    disabled, switched on, operation enabled), or None when already there."""
    if state is goal:
        return None
    if state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
        return Command.FAULT_RESET.value
    if goal is State.SWITCH_ON_DISABLED:
        return Command.DISABLE_VOLTAGE.value
    path = (State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
            State.OPERATION_ENABLED)
    if goal not in path:
        raise ValueError(f"{goal.value} is not a goal the master steers to")
    if state is State.QUICK_STOP_ACTIVE or state is State.NOT_READY_TO_SWITCH_ON:
        return Command.DISABLE_VOLTAGE.value
    here, there = path.index(state), path.index(goal)
    if here > there:
        return Command.SHUTDOWN.value if goal is State.READY_TO_SWITCH_ON else (
            Command.DISABLE_OPERATION.value)
    step = path[here + 1]
    return {
        State.READY_TO_SWITCH_ON: Command.SHUTDOWN.value,
        State.SWITCHED_ON: Command.SWITCH_ON.value,
        State.OPERATION_ENABLED: Command.ENABLE_OPERATION.value,
    }[step]
