"""A master nobody here wrote against the virtual slave: KickCAT (its Python binding, from
PyPI) scans a line of virtual drives on a veth, reads their identity and dictionary by CoE,
maps their process data, takes them INIT -> PRE-OP -> SAFE-OP -> OP and runs one in cyclic
synchronous torque, holding a loaded joint against gravity (issue 27, item 6).

Distributed clocks are not exercised: KickCAT's Python binding (2.5) exposes no DC call (the
C++ Bus has its DC set-up, the binding has none of it), so a KickCAT master here runs the line
SM-synchronous (free run). Its C++ DC set-up (resetSlaves + enableDC), and IgH EtherLab's, are
replayed frame by frame in tests/test_ethercat_dc_masters.py; this project's own master on DC is
in tests/test_ethercat_dc.py."""

import time

import kickcat
import pytest
from kickcat.mailbox.request import MessageStatus

from model import dynamics
from model.parameters import Payload, load_model
from protocol import esi_path, objects
from protocol.cia402 import State, state_from_statusword
from protocol.esi import load_esi
from sim_bus.ethercat.netns import SlaveProcess
from tests.conftest import as_a_real_time_master

pytestmark = [pytest.mark.root, pytest.mark.subprocess]

MODEL = load_model()
ESI = load_esi(esi_path())
LOAD = Payload(5.0, 0.0, 0.05)  # kg on the forearm: gravity the drive must hold
PACKED = MODEL.parameters.with_payload(LOAD).packed()
SLAVES = 2
P = MODEL.parameters
FRICTION_AND_OFFSET = (P.dry_friction_motor + P.dry_friction_joint
                       + abs(P.torque_offset_joint) + 0.2)  # N.m, 0.2 for the PD's residue
IDENTITY = 0x1018  # CiA 301 identity object: 1 vendor, 2 product, 3 revision
HOLD_AT = -0.5  # rad, where the joint is held
STIFFNESS, DAMPING = 60.0, 6.0  # N.m/rad, N.m.s/rad: a plain holding PD beside gravity
HOLD_CYCLES = 1200  # drive periods lifting and holding: settles within the first half
FALL_CYCLES = 200  # drive periods released (no torque) at the end: the joint falls
# KickCAT's link timeout: how long it waits for a frame to come back. It waits this long for
# each broadcast write too (for an answer on the absent redundant port), so a scan costs about
# a hundred of them. Its default, 2 ms, is shorter than a slave in a Python process answers on
# a loaded 2-core host: a datagram lost 1 run in 3 at load 8, both sides at real-time priority.
# 10 ms still lost one mid-run in 2 of 4 quiet clean-clone suite runs on 2026-12-04 (in the
# second, the test ran alone under the suite's lock). The stalls are the host's: ten runs of this
# test at 10 ms (all passed) beside a sleeping 1 kHz loop on each CPU at a priority above both
# sides (`driver.host_floor.FloorBeside`) saw 14 wake-ups 5-9.7 ms late in 85 s, 11 of them on
# both CPUs at once (the whole virtual machine off its CPUs; 2 % steal in /proc/stat). Below
# the sync manager watchdog (WATCHDOG), a late frame is not a lost drive.
LINK_TIMEOUT = 0.030  # s
WATCHDOG = 0.1  # s, the sync manager watchdog KickCAT sets at init
STATE_TIMEOUT = 2.0  # s for the line to reach a requested state
PERIOD = 0.001  # s, the drives' cycle period (0x1006 left unconfigured: 1 ms)

# the sample (TxPDO 0x1A00) and command (RxPDO 0x1600) as the ESI lays them out
STATUSWORD_AT, POSITION_AT, VELOCITY_AT, TORQUE_AT = 0, 2, 6, 10
COMMAND_BYTES, SAMPLE_BYTES = 4, 18
# CiA 402 controlwords walking the state machine to OPERATION ENABLED
NEXT_CONTROLWORD = {State.SWITCH_ON_DISABLED: 0x0006, State.READY_TO_SWITCH_ON: 0x0007,
                    State.SWITCHED_ON: 0x000F, State.OPERATION_ENABLED: 0x000F}


def sdo_message(bus: kickcat.Bus, message) -> MessageStatus:
    """Drive KickCAT's mailbox until `message` completes; its status."""
    while message.status() == MessageStatus.RUNNING:
        bus.process_mailboxes()
    return message.status()


def read_u32(bus: kickcat.Bus, slave: kickcat.Slave, index: int, subindex: int) -> int:
    data = bus.read_sdo(slave, index, subindex, kickcat.Access.PARTIAL, 4, 1.0)
    return int.from_bytes(data, "little")


def holding_torque(position: float, velocity: float) -> float:
    """Gravity compensation plus a PD towards HOLD_AT (N.m)."""
    return (float(dynamics.gravity_torque(position, PACKED))
            + STIFFNESS * (HOLD_AT - position) - DAMPING * velocity)


def sample_of(slave: kickcat.Slave) -> tuple[int, float, float, int]:
    """(statusword, position rad, velocity rad/s, torque actual per mille) from the inputs."""
    data = slave.input_data
    word = int.from_bytes(data[STATUSWORD_AT:STATUSWORD_AT + 2], "little")
    increments = int.from_bytes(data[POSITION_AT:POSITION_AT + 4], "little", signed=True)
    velocity = int.from_bytes(data[VELOCITY_AT:VELOCITY_AT + 4], "little", signed=True)
    torque = int.from_bytes(data[TORQUE_AT:TORQUE_AT + 2], "little", signed=True)
    return (word, objects.increments_to_position(increments),
            objects.increments_to_position(velocity), torque)


def command(slave: kickcat.Slave, controlword: int, torque_permille: int) -> None:
    slave.set_output_bytes(controlword.to_bytes(2, "little")
                           + torque_permille.to_bytes(2, "little", signed=True))


@pytest.mark.real_time
def test_kickcat_takes_the_line_to_op_and_holds_a_loaded_joint_in_cst(link):
    started = time.monotonic()
    # KickCAT at the real-time master's priority, as a master runs: at normal priority on a
    # loaded host its frames came back after its timeout (LOST datagrams) 3 runs in 3 at load 9
    with SlaveProcess(link, SLAVES, MODEL, LOAD), as_a_real_time_master():
        with link.entered():  # the raw socket is made in the line's namespace
            wire = kickcat.create_link(link.master_port, "")
        wire.set_timeout(LINK_TIMEOUT)
        bus = kickcat.Bus(wire)

        # scan: detection, station addresses, SII, mailboxes, PRE-OP
        bus.init(WATCHDOG)
        slaves = bus.slaves()
        assert len(slaves) == SLAVES
        assert [bus.get_state(slave) for slave in slaves] == [kickcat.State.PREOP] * SLAVES
        first = slaves[0]

        # identity and dictionary through KickCAT's CoE mailbox
        for slave in slaves:
            assert read_u32(bus, slave, IDENTITY, 1) == ESI.vendor_id
            assert read_u32(bus, slave, IDENTITY, 2) == ESI.product_code
            assert read_u32(bus, slave, IDENTITY, 3) == ESI.revision
        # the SDO Information service: object and entry descriptions
        name, _ = bus.read_object_description(first, objects.STATUSWORD)
        assert name == "Statusword"
        name, description = bus.read_entry_description(first, objects.TARGET_TORQUE, 0)
        assert "integer 16" in description and "RxPDO" in description, description
        assert name == "Target torque"
        rated_torque = read_u32(bus, first, objects.RATED_TORQUE, 0) / objects.MILLI  # N.m
        assert rated_torque > 0

        # mode of operation by SDO download, read back. (A refused download is not tried:
        # KickCAT 2.5 drops every SDO abort, which ETG.1000.6 sends as an SDO request, before
        # the waiting transfer sees it; fixed in KickCAT 2.6, PR #400.)
        write = first.mailbox.write_sdo(objects.MODES_OF_OPERATION, 0, False,
                                        bytes([objects.MODE_CYCLIC_SYNC_TORQUE]), 1.0)
        assert sdo_message(bus, write) == MessageStatus.SUCCESS
        display = bus.read_sdo(first, objects.MODES_OF_OPERATION_DISPLAY, 0,
                               kickcat.Access.PARTIAL, 1, 1.0)
        assert display == bytes([objects.MODE_CYCLIC_SYNC_TORQUE])

        # process data mapped from what the slaves say (SII sync managers, CoE PDO assignment)
        bus.create_mapping()
        assert [(s.input_size, s.output_size) for s in slaves] == \
            [(SAMPLE_BYTES, COMMAND_BYTES)] * SLAVES

        bus.request_state(kickcat.State.SAFE_OP)
        bus.wait_for_state(kickcat.State.SAFE_OP, STATE_TIMEOUT)
        for slave in slaves:
            command(slave, 0, 0)
        bus.process_data()
        bus.request_state(kickcat.State.OPERATIONAL)
        bus.wait_for_state(kickcat.State.OPERATIONAL, STATE_TIMEOUT, bus.process_data)
        assert [bus.get_state(slave) for slave in slaves] == \
            [kickcat.State.OPERATIONAL] * SLAVES

        # cyclic synchronous torque: enable (6, 7, 15), lift the joint from where it hangs to
        # HOLD_AT and hold it there against gravity, then command no torque and let it fall
        # at the drive's period, as a master cycles: back to back, the master (real-time,
        # polling its socket) and the slaves' process kept both cores busy, and one run in
        # about ten lost a datagram mid-run on a quiet host
        states, trace = [], []
        due = time.perf_counter()
        for cycle in range(HOLD_CYCLES + FALL_CYCLES):
            due += PERIOD
            time.sleep(max(0.0, due - time.perf_counter()))
            bus.process_data()  # raises on a wrong working counter
            word, position, velocity, torque_actual = sample_of(first)
            state = state_from_statusword(word)
            states.append(state)
            torque = holding_torque(position, velocity) if cycle < HOLD_CYCLES else 0.0
            permille = round(torque / rated_torque * objects.MILLI)
            trace.append((position, permille, torque_actual))
            command(first, NEXT_CONTROLWORD.get(state, 0), permille)
            command(slaves[1], 0, 0)
        assert [bus.get_state(slave) for slave in slaves] == \
            [kickcat.State.OPERATIONAL] * SLAVES

        enabled_at = states.index(State.OPERATION_ENABLED)
        assert enabled_at <= 6, states[:10]  # 6, 7, 15 each take a cycle or two
        assert all(s is State.OPERATION_ENABLED for s in states[enabled_at:])
        hanging = trace[enabled_at][0]
        assert abs(hanging - HOLD_AT) > 0.3, hanging  # the joint has a way to go
        settled = trace[HOLD_CYCLES // 2:HOLD_CYCLES]
        # held near HOLD_AT (dry friction and the torque offset leave the PD a few hundredths
        # of a radian) and still
        positions = [position for position, _, _ in settled]
        assert all(abs(position - HOLD_AT) < 0.05 for position in positions), settled[-1]
        assert max(positions) - min(positions) < 0.01, (min(positions), max(positions))
        # by the drive making the torque gravity takes there, as commanded (the sample lags a
        # cycle), give or take what friction and offset carry
        gravity = float(dynamics.gravity_torque(HOLD_AT, PACKED))
        held = sum(commanded for _, commanded, _ in settled) / len(settled) / objects.MILLI
        assert abs(held * rated_torque - gravity) < FRICTION_AND_OFFSET, (held, gravity)
        for (_, commanded, _), (_, _, actual) in zip(settled, settled[1:], strict=False):
            assert abs(actual - commanded) <= 0.05 * objects.MILLI, (commanded, actual)
        # released, the joint falls back the way it hangs
        fallen = trace[-1][0]
        assert (fallen - HOLD_AT) * (hanging - HOLD_AT) > 0 and abs(fallen - HOLD_AT) > 0.05, \
            (HOLD_AT, fallen, hanging)
    assert time.monotonic() - started < 60
