"""A frame-level master for a `Segment` in this process, as SOEM sets a line up: mailbox sync
managers, the PDO assignment's SM2/SM3, FMMU0 (outputs) and FMMU1 (inputs) of every slave
in one logical image (all outputs, then all inputs), the process data watchdog, OP; then one
LRW a cycle. Used by tests/test_segment_batch.py and, as `python3 -m tests.segment_frames`,
to time a frame through talos_32's line stage by stage.
"""

import argparse
import statistics
import struct
import time

import numpy as np

from model.parameters import Payload
from protocol import ethercat as ec
from protocol import objects
from protocol.dictionary import mappable_object
from protocol.pdo import PdoLayout
from sim_bus.device import Cia402Device
from sim_bus.ethercat.dc import (
    REG_RECEIVE_TIME_PORT0,
    REG_RECEIVE_TIME_UNIT,
    REG_START_TIME,
    REG_SYNC0_CYCLE_TIME,
    REG_SYNC_ACTIVATION,
    REG_SYSTEM_TIME_DELAY,
    REG_SYSTEM_TIME_OFFSET,
)
from sim_bus.ethercat.segment import Segment, pass_frame

Cmd = ec.Command
AL = ec.AlState
SHUTDOWN, SWITCH_ON, ENABLE = 0x06, 0x07, 0x0F
FIRST_STATION = 0x1001


class FrameMaster:
    """Drives `segment` frame by frame; `now` is the frames' time (s)."""

    def __init__(self, segment: Segment):
        self.segment = segment
        self.now = 0.0
        self.count = len(segment.escs)
        for k in range(self.count):
            self.send([(Cmd.APWR, 0, (-k & 0xFFFF) | ec.REG_STATION_ADDRESS << 16,
                        struct.pack("<H", FIRST_STATION + k))])

    def send(self, datagrams: list) -> bytearray:
        frame = bytearray(ec.encode_frame(datagrams))
        assert self.segment.process(frame, len(frame), self.now)
        return frame

    def write(self, slave: int, register: int, data: bytes) -> int:
        frame = self.send([(Cmd.FPWR, 0, FIRST_STATION + slave | register << 16, data)])
        return ec.datagram_result(frame, ec.datagram_spans(frame)[0])[1]

    def read(self, slave: int, register: int, size: int) -> bytes:
        frame = self.send([(Cmd.FPRD, 0, FIRST_STATION + slave | register << 16, bytes(size))])
        return ec.datagram_result(frame, ec.datagram_spans(frame)[0])[0]

    def request(self, state: int) -> None:
        for k in range(self.count):
            self.write(k, ec.REG_AL_CONTROL, struct.pack("<H", state | ec.AL_ERROR))

    def states(self) -> list[int]:
        return [struct.unpack("<H", self.read(k, ec.REG_AL_STATUS, 2))[0]
                for k in range(self.count)]

    def start(self, operational: bool = True) -> None:
        """INIT -> SAFE-OP with the image mapped, OP requested (entered with the first
        outputs) unless not `operational`."""
        self.map_process_data()
        self.request(AL.SAFE_OP)
        assert self.states() == [AL.SAFE_OP] * self.count
        if operational:
            self.request(AL.OP)

    def map_process_data(self) -> None:
        """INIT -> PRE-OP (mailbox sync managers), then the PDO sync managers, FMMUs and the
        process data watchdog written in PRE-OP: where a master leaves the line before it
        sets distributed clocks up (IgH) or asks for SAFE-OP (SOEM)."""
        segment = self.segment
        esi = segment.esi
        for k in range(self.count):
            record = b""
            for kind in ("MBoxOut", "MBoxIn"):
                sm = esi.sync_manager(kind)
                record += ec.SYNC_MANAGER.pack(sm.start, sm.default_size, sm.control, 0, 1, 0)
            self.write(k, ec.REG_SM0, record)
        self.request(AL.PRE_OP)
        assert self.states() == [AL.PRE_OP] * self.count
        firmware = segment.firmwares[0]
        self.layouts = tuple(PdoLayout(0, tuple(
            mappable_object(firmware.device.dictionary, entry)
            for entry in firmware.objects.assigned_entries(assign)))
            for assign in (ec.RXPDO_ASSIGN, ec.TXPDO_ASSIGN))
        self.out_size, self.in_size = (layout.size for layout in self.layouts)
        for k in range(self.count):
            out_sm, in_sm = esi.sync_manager("Outputs"), esi.sync_manager("Inputs")
            base = ec.REG_SM0 + esi.sm_number("Outputs") * ec.SM_SIZE
            self.write(k, base, ec.SYNC_MANAGER.pack(out_sm.start, self.out_size,
                                                     out_sm.control, 0, 1, 0)
                       + ec.SYNC_MANAGER.pack(in_sm.start, self.in_size, in_sm.control,
                                              0, 1, 0))
            self.write(k, ec.REG_FMMU0, ec.FMMU.pack(
                k * self.out_size, self.out_size, 0, 7, out_sm.start, 0, ec.FMMU_WRITE, 1)
                + ec.FMMU.pack(self.count * self.out_size + k * self.in_size, self.in_size,
                               0, 7, in_sm.start, 0, ec.FMMU_READ, 1))
            self.write(k, ec.REG_WATCHDOG_TIME_PROCESS_DATA, struct.pack("<H", 1000))  # 100 ms

    def start_dc(self, shift: float = 0.5e-3, period: float = 1e-3) -> None:
        """From SAFE-OP, what SOEM's ecx_configdc and ecx_dcsync0 send: receive times
        latched, each slave's offset onto the master's time (`now` in ns) and its delay, SYNC0
        every `period` `shift` past the master's frames, starting 100 ms on; then OP
        requested (entered at the first SYNC0 with outputs)."""
        self.send([(Cmd.BWR, 0, REG_RECEIVE_TIME_PORT0 << 16, bytes(4))])
        parent_span = delay = 0
        for k in range(self.count):
            port0, port1 = struct.unpack("<II", self.read(k, REG_RECEIVE_TIME_PORT0, 8))
            (latched,) = struct.unpack("<Q", self.read(k, REG_RECEIVE_TIME_UNIT, 8))
            self.write(k, REG_SYSTEM_TIME_OFFSET,
                       struct.pack("<Q", (int(self.now * 1e9) - latched) % 2**64))
            span = (port1 - port0) % 2**32 if k < self.count - 1 else 0
            if k:
                delay += (parent_span - span) // 2
                self.write(k, REG_SYSTEM_TIME_DELAY, struct.pack("<I", delay))
            parent_span = span
        cycle = int(round(period * 1e9))
        for k in range(self.count):
            self.write(k, REG_SYNC_ACTIVATION, b"\x00")
            (now,) = struct.unpack("<Q", self.read(k, ec.REG_DC_SYSTEM_TIME, 8))
            start = (now + 100_000_000) // cycle * cycle + cycle + int(round(shift * 1e9))
            self.write(k, REG_START_TIME, struct.pack("<Q", start))
            self.write(k, REG_SYNC0_CYCLE_TIME, struct.pack("<I", cycle))
            self.write(k, REG_SYNC_ACTIVATION, b"\x03")
        self.request(AL.OP)

    def image(self, controlwords: np.ndarray, torques: np.ndarray) -> bytes:
        """The logical image an LRW carries: every slave's controlword and target torque (and
        zero for any other output), then room for the inputs."""
        outputs = np.zeros(self.count, self.layouts[0].dtype)
        outputs["f0"] = controlwords
        if len(self.layouts[0].objects) > 1:
            outputs["f1"] = torques
        return outputs.tobytes() + bytes(self.count * self.in_size)

    def lrw(self, controlwords: np.ndarray, torques: np.ndarray) -> bytearray:
        """The cyclic frame: one LRW of `image`, one cycle later."""
        self.now += 1e-3
        return self.send([(Cmd.LRW, 0, 0, self.image(controlwords, torques))])

    def inputs(self, frame: bytearray) -> np.ndarray:
        data, _ = ec.datagram_result(frame, ec.datagram_spans(frame)[0])
        return np.frombuffer(data[self.count * self.out_size:], self.layouts[1].dtype)


def enable_sequence(k: int, count: int) -> np.ndarray:
    """The controlwords of cycle k: shutdown, switch on, enable (then enabled)."""
    return np.full(count, (SHUTDOWN, SWITCH_ON, ENABLE)[min(k, 2)], dtype=np.int64)


def talos_devices(count: int | None = None) -> list[Cia402Device]:
    """talos_32's drives (the first `count` of the line) as `sim-bus --robot
    robots/talos_32.toml` makes them, in cyclic synchronous torque mode."""
    from robot.description import load_robot
    from sim_bus.embedded import make_device
    from sim_bus.plant import SensorNoise

    robot = load_robot("robots/talos_32.toml")
    devices = []
    for n, joint in enumerate(sorted(robot.joints, key=lambda joint: joint.address)[:count]):
        device = make_device(joint.model, Payload(), SensorNoise(seed=n), eds_path=joint.eds,
                             commissioned=True)
        device.write(objects.MODES_OF_OPERATION, 0, objects.MODE_CYCLIC_SYNC_TORQUE)
        devices.append(device)
    return devices


def _percentiles(seconds: list[float]) -> str:
    us = sorted(s * 1e6 for s in seconds)
    return (f"median {statistics.median(us):7.1f} us  p99 {us[int(0.99 * (len(us) - 1))]:7.1f} "
            f"us  max {us[-1]:7.1f} us")


def main() -> None:
    """Time talos_32's cyclic frame through the segment, stage by stage, batch off and on."""
    parser = argparse.ArgumentParser(prog="python3 -m tests.segment_frames")
    parser.add_argument("--frames", type=int, default=3000)
    parser.add_argument("--batch", choices=("on", "off", "both"), default="both")
    args = parser.parse_args()
    for batching in {"on": (True,), "off": (False,), "both": (False, True)}[args.batch]:
        segment = Segment(talos_devices())
        if not batching:
            segment.batch = None
        master = FrameMaster(segment)
        master.start()
        count = master.count
        torques = np.zeros(count, dtype=np.int64)
        for k in range(200):
            master.lrw(enable_sequence(k, count), torques)
        assert all(d.state.name == "OPERATION_ENABLED" for d in segment.drives.devices)
        stages = {name: [] for name in ("parse", "frame", "watchdogs")}
        clock = time.perf_counter
        for k in range(args.frames):
            torques[:] = (100 * np.sin(np.arange(count) + k / 100)).astype(np.int64)
            outputs = np.zeros(count, master.layouts[0].dtype)
            outputs["f0"], outputs["f1"] = ENABLE, torques
            frame = bytearray(ec.encode_frame([(Cmd.LRW, 0, 0, outputs.tobytes()
                                                + bytes(count * master.in_size))]))
            master.now += 1e-3
            t0 = clock()
            ec.datagram_spans(frame, len(frame))
            t1 = clock()
            assert segment.process(frame, len(frame), master.now)
            t2 = clock()
            segment.check_watchdogs(master.now)
            t3 = clock()
            stages["parse"].append(t1 - t0)
            stages["frame"].append(t2 - t1)
            stages["watchdogs"].append(t3 - t2)
        print(f"batch {'on ' if batching else 'off'}: {count} slaves, {args.frames} frames")
        for name, seconds in stages.items():
            print(f"  {name:10s} {_percentiles(seconds)}")
        if not batching:
            # the ESCs alone: the same frames with the firmware's cycle taken out
            for firmware in segment.firmwares:
                firmware.outputs_received = lambda esc: None
            escs_only = []
            for _ in range(args.frames // 3):
                frame = bytearray(ec.encode_frame([(Cmd.LRW, 0, 0, bytes(
                    count * (master.out_size + master.in_size)))]))
                master.now += 1e-3
                t0 = clock()
                pass_frame(segment.escs, frame, len(frame), master.now)
                escs_only.append(clock() - t0)
            print(f"  {'ESCs only':10s} {_percentiles(escs_only)} (FMMU/SM copies, no cycle)")


if __name__ == "__main__":
    main()
