"""A line's batch (`sim_bus.line_physics.DriveLine`) against the device it batches: the same
drives given the same outputs cycle for cycle, one set through `Cia402Device.cycle()` alone,
the other through the batch (which leaves the cycles it does not run to the device, as the
linked line does), must agree to 1e-12 on every position, velocity, current and reading and
exactly on every statusword, state and emergency, through enabling, a fault from leaving the
position window and its reset, scheduled faults (over-current trip, encoder glitch, torque
sensor saturation), a quick stop, a mode change, a payload change and friction that drifts with
time, whether looked at every cycle or after a hundred."""

import math
from dataclasses import replace

import numpy as np

from driver.clock import DriveClock
from driver.interface import SAMPLE_JOINT_TORQUE
from model import dynamics
from model.parameters import Payload, load_model
from protocol import objects
from sim_bus.device import LINE_KEYS
from sim_bus.embedded import make_device
from sim_bus.faults import Fault
from sim_bus.line_physics import DriveLine, _compiled_blocks, buffer_sizes, line_blocks
from sim_bus.plant import STATE_SIZE, SensorNoise

JOINTS = 4
CYCLES = 2000
OUTPUTS = ((objects.CONTROLWORD, 0), (objects.TARGET_TORQUE, 0), (objects.TARGET_CURRENT, 0))
SHUTDOWN, SWITCH_ON, ENABLE, QUICK_STOP, FAULT_RESET = 0x06, 0x07, 0x0F, 0x02, 0x80


def _drives() -> list:
    model = load_model()
    # joint 1's dry friction drifts (warm-up): its parameters change every cycle
    parameters = model.parameters
    warming = replace(model, parameters=parameters.with_effect("warm_up_friction", {
        **parameters.effects.section("warm_up_friction"), "excess_friction": 0.8,
        "time_constant": 0.4}))
    devices = []
    for j in range(JOINTS):
        device = make_device(warming if j == 1 else model, Payload(), SensorNoise(seed=j),
                             commissioned=True)
        device.write(objects.MODES_OF_OPERATION, 0, objects.MODE_CYCLIC_SYNC_TORQUE)
        devices.append(device)
    devices[1].schedule(Fault.ENCODER_GLITCH, 0.300)
    devices[2].schedule(Fault.TORQUE_SENSOR_SATURATED, 0.250)
    devices[3].schedule(Fault.OVERCURRENT_TRIP, 0.900)
    return devices


def _outputs(j: int, k: int) -> tuple[int, int, int]:
    """Joint j's controlword and targets at cycle k: enabled at staggered cycles, a torque
    target that drives joint 0 out of its window (a fault, reset at 1200), a quick stop on
    joint 2 at 700 and enabled again at 1100."""
    if k < 3 + j:
        controlword = (SHUTDOWN, SWITCH_ON, ENABLE)[min(k, 2)]
        controlword = SHUTDOWN if k < j else controlword
    else:
        controlword = ENABLE
    if j == 2 and 700 <= k < 1100:
        controlword = QUICK_STOP
    if j == 2 and 1100 <= k < 1103:
        controlword = (SHUTDOWN, SWITCH_ON, ENABLE)[k - 1100]
    if j in (0, 3) and 1200 <= k < 1204:
        controlword = (FAULT_RESET, SHUTDOWN, SWITCH_ON, ENABLE)[k - 1200]
    amplitude = 900 if j == 0 and k < 1200 else 200
    torque = int(round(amplitude * math.sin(2 * math.pi * k / (400 + 50 * j))))
    return controlword, torque, int(round(1500 * math.sin(k / 90)))


def _observed(device) -> tuple:
    values = device.values
    return (device.state, device.cycle_count, device.applied_current,
            tuple(values.get(key) for key in LINE_KEYS), tuple(values[key] for key in OUTPUTS))


def test_the_batch_runs_the_devices_cycles_exactly():
    reference, batched = _drives(), _drives()
    line = DriveLine(batched)
    emergencies = ([], [])
    for side, devices in enumerate((reference, batched)):
        for j, device in enumerate(devices):
            device.add_emergency_handler(
                lambda code, register, j=j, side=side: emergencies[side].append((j, code)))
    rows = np.arange(JOINTS)
    ran = 0
    for k in range(CYCLES):
        if k == 500:  # a mode change by SDO, a payload picked up
            for devices in (reference, batched):
                devices[1].write(objects.MODES_OF_OPERATION, 0,
                                 objects.MODE_CYCLIC_SYNC_CURRENT)
                devices[3].plant.set_payload(Payload(mass=2.0, x=0.0, y=0.05))
        outputs = np.array([_outputs(j, k) for j in range(JOINTS)], dtype=np.int64)
        for j, device in enumerate(reference):
            device.write_outputs(OUTPUTS, tuple(int(v) for v in outputs[j]))
            device.cycle()
        done = line.cycle(rows, outputs[:, 0], OUTPUTS, [outputs[:, 1], outputs[:, 2]])
        ran += int(done.sum())
        for j in np.flatnonzero(~done):  # what the slave's firmware does without a batch
            batched[j].write_outputs(OUTPUTS, tuple(int(v) for v in outputs[j]))
            batched[j].cycle()
        if 1300 <= k < 1700 and k % 100:
            continue  # unobserved, the batch's cycles pile up before they are written back
        for j in range(JOINTS):
            expected, got = reference[j], batched[j]
            assert np.allclose(got.plant.state, expected.plant.state, rtol=0, atol=1e-12), (k, j)
            assert got.plant.cursor[0] == expected.plant.cursor[0], (k, j)
            assert _observed(got) == _observed(expected), (k, j)
        assert emergencies[1] == emergencies[0], k
    assert len(line.state[0]) == STATE_SIZE
    # the script's events happened, and the batch ran all but the cycles that had them
    codes = {code for _, code in emergencies[0]}
    assert {0x8612, 0x2310} <= codes, codes  # position window, over-current trip
    assert reference[2].state.name == "OPERATION_ENABLED"
    assert reference[1].injected and reference[2].injected
    assert CYCLES * JOINTS - 100 < ran < CYCLES * JOINTS - 10, ran
    # joint 1's warm-up excess went down as W exp(-t / tau): 0.8 N.m at 0, 5 mN.m at 2 s
    excess = line.packed[1, dynamics.EFFECT_OFFSET["warm_up_friction"] + 2]
    assert batched[1].plant.drifts and 0.004 < excess < 0.006, excess


def test_draws_renewed_a_few_a_cycle_keep_the_sequence_and_the_batch():
    """Two lines of the same drives under the same outputs for 3 000 cycles (past the 2 048
    a batch of noise draws lasts): one renews a drive's draws a cycle once half are used
    (`DriveLine.renew_draws`), the other only when they run out, in the cycle (as before).
    Every state and reading is the same, to the last bit, and only the early-renewing line
    keeps every cycle in its batch: the other's drives all leave it in the same cycle."""
    def line_of_drives() -> DriveLine:
        devices = [make_device(load_model(), Payload(), SensorNoise(seed=j), commissioned=True)
                   for j in range(JOINTS)]
        for device in devices:
            device.write(objects.MODES_OF_OPERATION, 0, objects.MODE_CYCLIC_SYNC_TORQUE)
        return DriveLine(devices)

    early, late = line_of_drives(), line_of_drives()
    rows = np.arange(JOINTS)
    out_of_batch = ([], [])
    renewed = 0
    for k in range(3000):
        controlword = (SHUTDOWN, SWITCH_ON, ENABLE)[min(k, 2)]
        outputs = np.array([(controlword, int(40 * math.sin(k / 50 + j)), 0)
                            for j in range(JOINTS)], dtype=np.int64)
        for side, line in enumerate((early, late)):
            done = line.cycle(rows, outputs[:, 0], OUTPUTS, [outputs[:, 1], outputs[:, 2]])
            for j in np.flatnonzero(~done):
                line.devices[j].write_outputs(OUTPUTS, tuple(int(v) for v in outputs[j]))
                line.devices[j].cycle()
                if k > 2:
                    out_of_batch[side].append((k, int(j)))
        renewed += early.renew_draws(most=1)
    np.testing.assert_array_equal(early.state, late.state)
    for a, b in zip(early.devices, late.devices, strict=True):
        assert _observed(a) == _observed(b)
    assert out_of_batch[0] == []
    assert out_of_batch[1] == [(2047, j) for j in range(JOINTS)]  # 2 draws a cycle
    assert renewed == 2 * JOINTS  # at 1 024 cycles and at 2 048, one drive a cycle


def _three_elbows_on_a_line():
    from pathlib import Path

    from robot.description import JointSpec, RobotSpec, default_reference
    from robot.wiring import open_robot

    model = load_model()
    spec = RobotSpec(
        name="line3", period_us=1000,
        joints=tuple(JointSpec(f"joint_{k}", "ethercat:line0", k, model, None, {},
                               default_reference(model.limits)) for k in range(3)),
        bitrates={}, source=Path("<three elbows on one line>"))
    connection = open_robot(spec, sim=True, clock=DriveClock(), seed=0, period=1e-3,
                            response_timeout=1.0,
                            faults=[("joint_1", Fault.TORQUE_SENSOR_SATURATED, 0.1)])
    connection.group.start()
    return connection


def test_the_linked_line_in_a_batch_is_the_line_slave_by_slave():
    """The same robot linked twice, one line cycling its slaves in the batch and the other
    slave by slave through their ESCs and firmware: the master sees the same samples, the
    slaves' sync manager buffers and cycle counts are the same, through a sensor fault."""
    batched, single = _three_elbows_on_a_line(), _three_elbows_on_a_line()
    try:
        single.group.drives[0].transport.line.master._image = None
        masters = [c.group.drives[0].transport.line.master for c in (batched, single)]
        assert masters[0]._image is not None
        saturated = in_batch = 0
        for k in range(300):
            currents = np.array([0.5 * math.sin(k / 40 + j) for j in range(3)])
            tables = []
            for connection in (batched, single):
                tables.append(connection.group.sync())
                connection.group.warnings()
                connection.group.command_currents(currents)
            np.testing.assert_array_equal(tables[0], tables[1], err_msg=f"cycle {k}")
            saturated += int(np.isnan(tables[0][:, SAMPLE_JOINT_TORQUE]).sum())
            in_batch += masters[0]._image._seen != -1  # the last exchange was all batched
        assert saturated == 1 and batched.devices["joint_1"].injected
        assert in_batch > 280, in_batch
        for a, b in zip(*(m.slaves for m in masters), strict=True):
            assert a.input == b.input and a._firmware.cycles == b._firmware.cycles
            for start, length in (a._outputs, a._inputs):
                assert a._esc.memory[start:start + length] == b._esc.memory[start:start + length]
        assert [d.cycle_count for d in batched.devices.values()] == [
            d.cycle_count for d in single.devices.values()]
        assert masters[0]._wkc == masters[1]._wkc == 9
    finally:
        batched.close()
        single.close()


def test_the_lines_arrays_are_cut_from_its_buffers_alike_in_python_and_compiled():
    """`line_blocks` cuts a line's two buffers into its arrays once for Python and once in
    the compiled cycle (`advance_blocks`): both cuts give every array the same elements, and
    the line's named arrays are C-contiguous views of its buffers (the types `advance_line`
    is compiled for, whoever calls it)."""
    line = DriveLine(_drives()[:3])
    count, size = len(line), line.packed.shape[1]
    ints, reals = line._buffers
    assert (ints.size, reals.size) == buffer_sizes(count, size)
    ints[:], reals[:] = np.arange(ints.size), np.arange(reals.size) + 0.5
    python = line_blocks(ints, reals, count, size)
    compiled = _compiled_blocks(ints, reals, count, size)
    for mine, theirs in zip(python, compiled, strict=True):
        np.testing.assert_array_equal(mine, theirs)
    # every element of both buffers in exactly one array
    assert sorted(np.concatenate([a.ravel() for a in python if a.dtype == np.int64])) == list(
        ints)
    assert sum(a.size for a in python if a.dtype == np.float64) == reals.size
    for name in ("_controlword", "_next_due", "_cycles", "cursor", "flags", "outputs",
                 "ranges", "values", "torque_targets", "current_targets", "applied",
                 "terms", "state", "packed", "packed_braked", "draws"):
        array = getattr(line, name)
        assert array.flags.c_contiguous and (np.shares_memory(array, ints)
                                             or np.shares_memory(array, reals)), name
    assert line.state.shape == (count, STATE_SIZE) and line.packed_braked.shape == (count, size)
