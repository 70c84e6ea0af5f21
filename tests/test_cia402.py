import pytest

from protocol import cia402
from protocol.cia402 import Command, State


@pytest.mark.parametrize("state", list(State))
def test_statusword_round_trip(state):
    assert cia402.state_from_statusword(cia402.statusword_for(state)) is state
    assert cia402.state_from_statusword(cia402.statusword_for(state, internal_limit=True)) is state


def test_enable_sequence_walks_the_standard_path():
    state, words = State.SWITCH_ON_DISABLED, []
    while (word := cia402.controlword_toward(state, State.OPERATION_ENABLED)) is not None:
        words.append(word)
        previous = words[-2] if len(words) > 1 else 0
        state = cia402.next_state(state, cia402.command_from_controlword(word, previous))
    assert words == [0x06, 0x07, 0x0F]
    assert state is State.OPERATION_ENABLED


def test_fault_reset_needs_a_rising_edge():
    assert cia402.command_from_controlword(0x80, 0x00) is Command.FAULT_RESET
    assert cia402.command_from_controlword(0x80, 0x80) is None
    assert cia402.next_state(State.FAULT, Command.FAULT_RESET) is State.SWITCH_ON_DISABLED
    assert cia402.next_state(State.FAULT, Command.ENABLE_OPERATION) is State.FAULT


def test_quick_stop_and_disable_voltage():
    assert cia402.command_from_controlword(0x02, 0x0F) is Command.QUICK_STOP
    assert cia402.next_state(State.OPERATION_ENABLED, Command.QUICK_STOP) is (
        State.QUICK_STOP_ACTIVE)
    assert cia402.next_state(State.QUICK_STOP_ACTIVE, Command.ENABLE_OPERATION) is (
        State.QUICK_STOP_ACTIVE)
    assert cia402.next_state(State.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE) is (
        State.SWITCH_ON_DISABLED)
    assert cia402.controlword_toward(State.FAULT, State.OPERATION_ENABLED) == 0x80


def test_unknown_statusword_is_refused():
    with pytest.raises(ValueError, match="0x0001"):
        cia402.state_from_statusword(0x0001)


def test_a_held_command_leaves_the_state_it_led_to():
    """The virtual drive skips a repeated controlword on that ground (sim_bus.device)."""
    for state in State:
        for controlword in range(0x100):
            command = cia402.command_from_controlword(controlword, controlword)
            reached = cia402.next_state(state, command)
            assert cia402.next_state(reached, command) is reached, (state, hex(controlword))
    assert cia402.next_state(State.QUICK_STOP_ACTIVE, Command.QUICK_STOP) is (
        State.QUICK_STOP_ACTIVE)
