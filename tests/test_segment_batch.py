"""The segment's batch (`sim_bus.ethercat.frame_batch`) passes a frame exactly as the slaves
one by one do: the same frames go through two lines of the same drives, one with the batch
and one without, and every answer, every drive and every ESC's memory must be the same, through
an enable sequence, sensor faults, an overcurrent trip, a slave leaving OP on its own and
brought back, a quick stop, mixed frames (AL status reads, a DC time write, a watchdog status
read), CoE traffic beside the cycle (SDO uploads, a download that changes a drive's current
limit) and a process data watchdog expiry with the drives left to run alone."""

import struct

import numpy as np

from protocol import ethercat as ec
from protocol import objects
from sim_bus.ethercat.segment import Segment, pass_frame
from sim_bus.faults import Fault
from tests.segment_frames import ENABLE, FIRST_STATION, FrameMaster, talos_devices

Cmd = ec.Command
SLAVES = 6
CYCLES = 2000
QUICK_STOP, FAULT_RESET = 0x02, 0x80


def _line(batching: bool) -> FrameMaster:
    devices = talos_devices(SLAVES)
    devices[1].schedule(Fault.ENCODER_GLITCH, 0.300)
    devices[2].schedule(Fault.TORQUE_SENSOR_SATURATED, 0.250)
    devices[3].schedule(Fault.OVERCURRENT_TRIP, 0.900)
    devices[4].schedule(Fault.LEAVES_OP, 0.600)
    segment = Segment(devices)
    if not batching:
        segment.batch = None
    master = FrameMaster(segment)
    master.start()
    return master


def _controlwords(k: int) -> np.ndarray:
    """Each slave's controlword at cycle k: enabled at staggered cycles, slave 3 reset after
    its trip, slave 5 quick-stopped for a while, every slave enabled again after the
    watchdog (1600)."""
    words = np.full(SLAVES, ENABLE, dtype=np.int64)
    for j in range(SLAVES):
        start = 0 if k < 1600 else 1600
        if k - start < 3 + j:
            words[j] = (0x06, 0x07, ENABLE)[min(max(k - start - j, 0), 2)]
    if 950 <= k < 954:
        words[3] = (FAULT_RESET, 0x06, 0x07, ENABLE)[k - 950]
    if 400 <= k < 500:
        words[5] = QUICK_STOP
    elif 500 <= k < 503:
        words[5] = (0x06, 0x07, ENABLE)[k - 500]
    if 1600 <= k < 1601:
        words[:] = FAULT_RESET
    return words


def _frame(master: FrameMaster, k: int) -> list:
    """Cycle k's datagrams: the LRW, and in some cycles what a master adds to it."""
    count = master.count
    outputs = np.zeros(count, master.layouts[0].dtype)
    outputs["f0"] = _controlwords(k)
    outputs["f1"] = (300 * np.sin(np.arange(count) + k / 70)).astype(np.int64)
    if k == 800:  # slave 0's torque past its trip: the device's own cycle faults it
        outputs["f1"][0] = 32000
    datagrams = [(Cmd.LRW, 0, 0, outputs.tobytes() + bytes(count * master.in_size))]
    if k % 7 == 0:
        datagrams.append((Cmd.BRD, 0, ec.REG_AL_STATUS << 16, bytes(2)))
    if k % 5 == 0:
        datagrams.insert(0, (Cmd.FRMW, 0, FIRST_STATION | ec.REG_DC_SYSTEM_TIME << 16,
                             bytes(8)))
    if k % 97 == 0:  # a register the batch leaves alone: slave by slave
        datagrams.append((Cmd.APRD, 0, ec.REG_WATCHDOG_STATUS_PROCESS_DATA << 16, bytes(2)))
    return datagrams


def _sdo(master: FrameMaster, k: int) -> bytes | None:
    """Cycle k's CoE traffic, in frames of its own as a master's mailbox runs beside the
    cycle: an upload of a slave's position now and then, one download of slave 2's current
    limit (its drive's terms change); the reply read from the mailbox-in buffer."""
    if k == 700:
        sdo = ec.SDO_HEADER.pack(0x23 | 2 << 2, objects.MAX_CURRENT, 0) + bytes((200, 0, 0, 0))
        slave = 2
    elif k % 11 == 4:
        sdo = ec.SDO_HEADER.pack(0x40, objects.POSITION_ACTUAL, 0) + bytes(4)
        slave = k % SLAVES
    else:
        return None
    esi = master.segment.esi
    out_box, in_box = esi.sync_manager("MBoxOut"), esi.sync_manager("MBoxIn")
    body = ec.COE_HEADER.pack(ec.COE_SDO_REQUEST << ec.COE_SERVICE_SHIFT) + sdo
    # the mailbox counter: 1 to 7, a new one each message (a repeated one is a repeat)
    master.mailbox_counter = getattr(master, "mailbox_counter", 0) % 7 + 1
    message = ec.MAILBOX_HEADER.pack(len(body), 0, 0,
                                     ec.MAILBOX_TYPE_COE | master.mailbox_counter << 4)
    assert master.write(slave, out_box.start, (message + body).ljust(out_box.default_size,
                                                                     b"\0")) == 1
    return master.read(slave, in_box.start, in_box.default_size)


def _polls(master: FrameMaster, k: int) -> list[bytearray]:
    """Cycle k's frames of register reads beside the cycle, as SOEM sends them: the line's
    AL status (one BRD), a slave's mailbox-in status (one FPRD)."""
    frames = []
    if k % 10 == 3:
        frames.append(master.send([(Cmd.BRD, 0, ec.REG_AL_STATUS << 16, bytes(2))]))
    if k % 3 == 1:
        status = ec.REG_SM0 + ec.SM_SIZE + ec.SM_OFFSET_STATUS
        frames.append(master.send([(Cmd.FPRD, 0, FIRST_STATION + k % SLAVES | status << 16,
                                    bytes(2))]))
    return frames


def _devices(master: FrameMaster) -> list:
    return [(d.state, d.cycle_count, d.applied_current, d.plant.position, d.master_loss,
             sorted(d.values.items())) for d in master.segment.drives.devices]


def test_the_batch_passes_frames_exactly_as_the_slaves_one_by_one():
    batched, single = _line(True), _line(False)
    assert batched.segment.batch is not None
    seen = set()
    sdo_replies = 0
    for k in range(CYCLES):
        for master in (batched, single):
            master.now += 1e-3
            if k == 1500:  # the master away for 150 ms: every watchdog expires
                master.now += 0.150
                master.segment.check_watchdogs(master.now)
        frames = [m.send(_frame(m, k)) for m in (batched, single)]
        assert frames[0] == frames[1], f"cycle {k}"
        polls = [_polls(m, k) for m in (batched, single)]
        assert polls[0] == polls[1], f"cycle {k}"
        replies = [_sdo(m, k) for m in (batched, single)]
        assert replies[0] == replies[1], f"cycle {k}"
        if replies[0] is not None:
            sdo_replies += 1
        for master in (batched, single):
            master.segment.check_watchdogs(master.now)
        if k in (1000, 1530):  # slave 4 left OP (1000) / all did (1530): back to OP
            for master in (batched, single):
                master.request(ec.AlState.SAFE_OP)
                master.request(ec.AlState.OP)
        if k % 100 == 0 or k in (601, 703, 801, 901, 1234, 1501):
            # what steady frames left in the batch's arrays, written as anything looking
            # at the slaves has it written
            batched.segment.batch.settle()
            assert _devices(batched) == _devices(single), f"cycle {k}"
            for a, b in zip(batched.segment.escs, single.segment.escs, strict=True):
                assert a.memory == b.memory, f"cycle {k}"
                assert a._watchdog_deadline == b._watchdog_deadline, f"cycle {k}"
        seen.add(tuple(s & 0x1F for s in struct.unpack(
            f"<{SLAVES}H", b"".join(batched.read(j, ec.REG_AL_STATUS, 2)
                                    for j in range(SLAVES)))) if k % 50 == 0 else ())
    assert [r["cycles"] for r in batched.segment.report()] == [
        r["cycles"] for r in single.segment.report()]
    assert _devices(batched) == _devices(single)
    assert sdo_replies > 150
    assert batched.segment.drives.devices[2].read(objects.MAX_CURRENT, 0) == 200
    # what happened happened: a slave out of OP with an error, the watchdog's drop, and the
    # batch carried most cycles
    assert any(ec.AlState.SAFE_OP | ec.AL_ERROR in states for states in seen), seen
    devices = batched.segment.drives.devices
    assert devices[3].injected and devices[4].injected
    assert "watchdog" in devices[0].master_loss  # the expiry reached the drives
    assert all(f.cycles > CYCLES - 200 for f in batched.segment.firmwares)
    assert batched.segment.batch.batched > 0.8 * CYCLES * SLAVES, batched.segment.batch.batched


def _dc_line(batching: bool) -> FrameMaster:
    devices = talos_devices(SLAVES)
    devices[2].schedule(Fault.ENCODER_GLITCH, 0.300)
    devices[3].schedule(Fault.OVERCURRENT_TRIP, 0.500)
    segment = Segment(devices)
    if not batching:
        segment.batch = None
    master = FrameMaster(segment)
    master.now = 5.0
    master.start(operational=False)
    master.start_dc()
    return master


def _dc_frame(master: FrameMaster, k: int) -> list:
    """A DC master's cycle k: the LRW and the reference clock's time (FRMW), sometimes an AL
    status read."""
    count = master.count
    outputs = np.zeros(count, master.layouts[0].dtype)
    outputs["f0"] = _controlwords(k - 200)  # shutdown until OP (at the first SYNC0), then on
    outputs["f1"] = (300 * np.sin(np.arange(count) + k / 70)).astype(np.int64)
    datagrams = [(Cmd.LRW, 0, 0, outputs.tobytes() + bytes(count * master.in_size)),
                 (Cmd.FRMW, 0, FIRST_STATION | ec.REG_DC_SYSTEM_TIME << 16, bytes(8))]
    if k % 7 == 0:
        datagrams.append((Cmd.BRD, 0, ec.REG_AL_STATUS << 16, bytes(2)))
    return datagrams


def _clock(clock) -> tuple:
    """A slave's distributed clock: its time control loop and its SYNC0."""
    return (clock._correction, clock._slew, clock._integral, clock._anchor_t,
            clock.next_sync0, clock.sync0_count)


LATE = (400, 460)  # cycles in which the DC master sends every other frame only


def test_the_batch_runs_sync0_exactly_as_the_slaves_one_by_one():
    """DC: frames a period apart, SYNC0 half a period after each; the batch moves the steady
    slaves' buffers and runs their SYNC0 cycles at once. Every answer, drive and ESC memory is
    the same as slave by slave, through OP on SYNC0, the enable sequence, a sensor fault, a
    trip and its reset, a quick stop, a master that skips every other frame for a while (its
    windows without outputs cycle the drives on what they hold), and slave 1 pushed off its
    window (its clock jumped) until it drops out with a sync error; most cycles ran in the
    batch."""
    batched, single = _dc_line(True), _dc_line(False)
    for k in range(1000):
        if k == 700:  # slave 1's SYNC0 now 10 us after the frames: inside the outputs' margin
            for master in (batched, single):
                slave = master.segment.escs[1]
                offset = int.from_bytes(slave.memory[0x0920:0x0928], "little")
                slave.memory[0x0920:0x0928] = ((offset + 490_000) % 2**64).to_bytes(8, "little")
        for master in (batched, single):
            master.now += 1e-3
            master.segment.run_sync0(master.now)
        if not (LATE[0] <= k < LATE[1] and k % 2):  # a late master: every other frame
            frames = [m.send(_dc_frame(m, k)) for m in (batched, single)]
            assert frames[0] == frames[1], f"cycle {k}"
        for master in (batched, single):
            master.segment.run_sync0(master.now + 0.6e-3)
            master.segment.check_watchdogs(master.now)
        if k % 100 == 0 or k in (LATE[0] + 1, LATE[1], 501, 701, 705, 720):
            assert _devices(batched) == _devices(single), f"cycle {k}"
            for a, b in zip(batched.segment.escs, single.segment.escs, strict=True):
                assert a.memory == b.memory, f"cycle {k}"
                assert _clock(a.dc) == _clock(b.dc), f"cycle {k}"
    assert _devices(batched) == _devices(single)
    report = batched.segment.report()
    assert [r["cycles"] for r in report] == [r["cycles"] for r in single.segment.report()]
    assert [r["al_status_code"] for r in report] == [0, 0x001A, 0, 0, 0, 0]
    assert report[1]["missed_sync0"] >= 4 and report[0]["missed_sync0"] == 30
    assert report[0]["state"] == "OPERATION_ENABLED" and report[3]["state"] == "FAULT"
    assert all(r["cycles"] > 850 for r in report)
    assert batched.segment.batch.batched > 0.8 * 1000 * SLAVES, batched.segment.batch.batched


def test_a_frame_of_addressed_datagrams_reaches_only_the_slaves_it_names():
    """SOEM's state read of a long line (an FPRD per slave in one frame, here with an FPWR and
    a datagram to nobody) passes each slave only its own datagrams: the same frame and
    memories as every slave looking at every datagram."""
    routed, whole = (FrameMaster(Segment(talos_devices(SLAVES))) for _ in range(2))
    datagrams = [(Cmd.FPRD, 0, FIRST_STATION + k | ec.REG_AL_STATUS << 16, bytes(6))
                 for k in range(SLAVES)]
    datagrams += [(Cmd.FPWR, 0, FIRST_STATION + 2 | ec.REG_AL_CONTROL << 16, b"\x02\x00"),
                  (Cmd.FPRD, 0, 0x7777 | ec.REG_AL_STATUS << 16, bytes(2)),
                  (Cmd.BRD, 0, ec.REG_AL_STATUS << 16, bytes(2))]
    frames = []
    for master in (routed, whole):
        frame = bytearray(ec.encode_frame(datagrams))
        spans = ec.datagram_spans(frame, len(frame))
        if master is routed:
            assert pass_frame(master.segment.escs, frame, len(frame), 0.0)
        else:
            for esc in master.segment.escs:
                esc.process(frame, memoryview(frame), spans)
            frame[ec.SOURCE_MAC_OFFSET] |= ec.SOURCE_MAC_PROCESSED_BIT
        frames.append(frame)
    assert frames[0] == frames[1]
    results = [ec.datagram_result(frames[0], s) for s in ec.datagram_spans(frames[0])]
    assert [wkc for _, wkc in results] == [1] * (SLAVES + 1) + [0, SLAVES]
    for a, b in zip(routed.segment.escs, whole.segment.escs, strict=True):
        assert a.memory == b.memory


def test_the_batch_passes_safe_op_frames_exactly_as_the_slaves_one_by_one():
    """SAFE-OP (free run): every output buffer cycles the drive on what it holds, the outputs
    ignored and the inputs sampled, as an ESC in SAFE-OP does; the batch does it for the
    whole line at once with the same frames, drives and memories as slave by slave, through
    outputs that would enable the drives (ignored), OP requested and entered at the next
    buffer, and back to SAFE-OP; most SAFE-OP cycles ran in the batch."""
    lines = []
    for batching in (True, False):
        segment = Segment(talos_devices(SLAVES))
        if not batching:
            segment.batch = None
        master = FrameMaster(segment)
        master.start(operational=False)
        lines.append(master)
    batched, single = lines
    safe_op_cycles = 0
    for k in range(400):
        if k in (200, 300):  # OP (entered at the next buffer), then back to SAFE-OP
            for master in lines:
                master.request(ec.AlState.OP if k == 200 else ec.AlState.SAFE_OP)
        for master in lines:
            master.now += 1e-3
        frames = [m.send(_frame(m, k + 200)) for m in lines]  # enabling from the start
        assert frames[0] == frames[1], f"cycle {k}"
        if k < 200:
            safe_op_cycles = batched.segment.batch.batched
        if k % 20 == 0 or k in (199, 201, 299, 301):
            batched.segment.batch.settle()
            assert _devices(batched) == _devices(single), f"cycle {k}"
            for a, b in zip(batched.segment.escs, single.segment.escs, strict=True):
                assert a.memory == b.memory, f"cycle {k}"
    states = [[d.state.name for d in m.segment.drives.devices] for m in lines]
    assert states[0] == states[1]
    # in SAFE-OP the enable never reached the drives; in OP it did
    assert batched.states() == [ec.AlState.SAFE_OP] * SLAVES
    assert all(r["cycles"] == 400 for r in batched.segment.report())
    assert [r["cycles"] for r in batched.segment.report()] == [
        r["cycles"] for r in single.segment.report()]
    assert safe_op_cycles > 0.9 * 200 * SLAVES, safe_op_cycles
