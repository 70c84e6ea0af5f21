"""The CANopen transport (canopen + python-can): `driver.transport.Transport` for one drive,
made of its bring-up (`canopen_bringup`), its row of the bus's cycle (`canopen_cycle`) and its
health watch (`canopen_health`). The bus's jobs (the cycle, frame counts, heartbeats) are the
bus's, once per bus, whatever the number of drives on it."""

import time
from collections.abc import Sequence
from pathlib import Path

import can
import canopen

from driver.canopen_bringup import SdoAccess, plan_pdos, write_pdos
from driver.canopen_cycle import BusCycle, PlannedPdo
from driver.canopen_health import MASTER_HEARTBEAT_CONSUMER_MS, Health, master_node_id
from driver.canopen_multicast import MulticastNetwork
from driver.clock import Clock, WallClock
from driver.interface import DriveError, DriveLost, ForeignMaster
from driver.transport import Transport
from protocol import cia301, cia402, eds_path, objects
from protocol.bus_spec import parse_bus_spec
from protocol.cia402 import State
from protocol.dictionary import default_value, has, load_dictionary, mapped_object, variable
from protocol.pdo import MappedObject

NOTIFIER_CYCLE = 0.05  # s; bounds how long closing the network waits for the receive thread
DEFAULT_HEARTBEAT_MS = 100  # the drive's producer period the master asks for (0x1017)
FOREIGN_TRAFFIC_WINDOW = 0.1  # s of listening for another master before resetting the drive
# s: the most the listening waits for the receive thread to catch up when the drive does not
# answer (a silent bus waits it all: only a drive that is off or stopped pays it)
FOREIGN_TRAFFIC_LIMIT = 1.0
CATCH_UP_STEP = 0.005  # s between looks at how far the receive thread has come


def open_network(bus_spec: str, bitrate: int | None = None) -> canopen.Network:
    """A connected canopen Network for a bus spec (see protocol.bus_spec); `bitrate` (bit/s)
    where the interface sets one. A udp_multicast bus gets the lean path
    (`driver.canopen_multicast`), every other interface python-can's and canopen's own."""
    config = parse_bus_spec(bus_spec)
    if config["interface"] == "udp_multicast":
        return MulticastNetwork(config)
    network = canopen.Network()
    network.NOTIFIER_CYCLE = NOTIFIER_CYCLE
    if bitrate is not None:
        config["bitrate"] = bitrate
    network.connect(**config)
    return network


class CanOpenTransport(Transport):
    """Drive `node_id` on `network`, described by `eds` (default: the shipped elbow EDS). With
    `owns_network` (one drive on its bus) the transport disconnects the network on close;
    drives sharing a bus leave that to whoever owns it (`driver.drive_group.CanOpenBus`).

    `clock`: what the bus's watchdogs measure time on (`driver.clock`: the wall clock, or
    drive time in lock-step; the first drive on a bus gives the bus its clock);
    `response_timeout` (s) bounds the wait for a cycle's TPDOs (default: the clock's).
    """

    def __init__(self, network: canopen.Network, node_id: int, *,
                 eds: str | Path | None = None, clock: Clock | None = None,
                 response_timeout: float | None = None,
                 heartbeat_ms: int = DEFAULT_HEARTBEAT_MS, owns_network: bool = True):
        if not 1 <= node_id <= 127:
            raise ValueError(f"node id {node_id} outside 1..127")
        self.network = network
        self.owns_network = owns_network
        self.node_id = node_id
        self.name = f"node {node_id}"
        self.dictionary = load_dictionary(eds if eds is not None else eds_path(), node_id)
        self.node = canopen.RemoteNode(node_id, self.dictionary)
        network.add_node(self.node)
        self.heartbeat_ms = heartbeat_ms
        self.master_id = master_node_id(node_id)
        self.period = 0.0
        self._warnings: list[str] = []
        self.sdo = SdoAccess(self.node, self.name)
        clock = clock if clock is not None else WallClock()
        self.bus_cycle = BusCycle.of(network, clock, response_timeout
                                     if response_timeout is not None else clock.response_timeout)
        self.clock = self.bus_cycle.clock
        self.row = self.bus_cycle.join(self.name, self._warnings)
        self.health = Health(network, self.node, self.name, clock=self.clock,
                             on_failure=self._fail, on_emergency=self._emergency,
                             warnings=self._warnings)
        self._plan: tuple[list[PlannedPdo], list[PlannedPdo], bool] | None = None
        self._closed = False

    # --- acyclic ----------------------------------------------------------------------------

    def boot(self, timeout: float) -> None:
        """Refuse a drive another master drives, then NMT reset communication and wait for
        the boot-up message."""
        self._refuse_if_driven()
        self.health.expect_boot()
        try:
            self.node.nmt.state = "RESET COMMUNICATION"
        except (can.CanError, OSError) as exc:
            raise DriveError(f"{self.name}: cannot send NMT: {exc}") from exc
        if not self.health.booted.wait(timeout):
            raise DriveLost(f"{self.name}: no boot-up message within {timeout} s "
                            "(is the drive powered and on this bus?)")
        self.bus_cycle.clear(self.row)

    def _fail(self, error: DriveError) -> None:
        self.bus_cycle.fail(self.row, error)

    def _emergency(self, code: int, register: int) -> None:
        self.bus_cycle.alarm = True  # the bus's segment looks at its drives' faults
        self.on_emergency(code, register)

    def _refuse_if_driven(self) -> None:
        """ForeignMaster if someone else is driving the drive: its SYNC or the drive's RPDOs
        on the bus while we listen (a master cycling at 10 Hz or faster is heard), or the
        drive already past switch on disabled. The listening lasts FOREIGN_TRAFFIC_WINDOW on
        the bus's clock: in lock-step (an in-process link, one master by construction) drive
        time gets there at once."""
        watched = {cia301.SYNC_COB_ID} | {base + self.node_id for base in cia301.RPDO_BASES}
        for n in range(objects.PDO_CHANNELS):
            if has(self.dictionary, objects.RPDO_COMM + n, 1):
                cob_id = default_value(variable(self.dictionary, objects.RPDO_COMM + n, 1))
                if not cob_id & cia301.PDO_INVALID and cob_id & cia301.COB_ID_MASK:
                    watched.add(cob_id & cia301.COB_ID_MASK)
        seen: dict[int, int] = {}

        def count(can_id: int, data: bytes, timestamp: float) -> None:
            seen[can_id] = seen.get(can_id, 0) + 1

        for cob_id in watched:
            self.network.subscribe(cob_id, count)
        try:
            self.clock.sleep_until(self.clock.now() + FOREIGN_TRAFFIC_WINDOW)
            # the drive's answer comes through the same receive thread as every frame
            # before it: once it is in, whatever another master sent in the window was
            # counted, however late a busy host ran that thread
            try:
                statusword = self.read(objects.STATUSWORD)
            except DriveError:
                # not answering: powered off, NMT stopped, or its answer late behind a busy
                # host's receive thread. Before the reset that follows (a reset of a drive
                # another master runs would stop that master's joint), listen until a frame
                # stamped after now has come through, or the limit
                statusword = None
                self._catch_up(time.time(), FOREIGN_TRAFFIC_LIMIT)
        finally:
            for cob_id in watched:
                self.network.unsubscribe(cob_id, count)
        if seen:
            kinds = {cia301.SYNC_COB_ID: "SYNC"}
            frames = ", ".join(f"{n} x 0x{cob_id:03X} ({kinds.get(cob_id, 'RPDO')})"
                               for cob_id, n in sorted(seen.items()))
            raise ForeignMaster(f"{self.name}: another master is driving it: {frames} while "
                                "listening before the reset")
        if statusword is None:
            return  # the boot-up wait says whether it is there at all
        state = cia402.state_from_statusword(statusword)
        # a drive stopping on its own (quick stop active: no torque, brake on) after its
        # master died is safe to take over; the NMT reset that follows powers it off
        if state not in (State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON, State.FAULT,
                         State.QUICK_STOP_ACTIVE):
            raise ForeignMaster(f"{self.name}: another master is driving it: the drive is "
                                f"already in '{state.value}' (statusword 0x{statusword:04X})")

    def _catch_up(self, stamp: float, limit: float) -> None:
        """Wait until the receive thread has passed a frame stamped `stamp` or later (the
        bus's frames up to then are counted), at most `limit` s of the bus's clock: a silent
        bus never does."""
        bus, clock = self.health.bus, self.clock
        deadline = clock.now() + limit
        while bus.last_stamp < stamp and clock.now() < deadline:
            clock.sleep_until(clock.now() + CATCH_UP_STEP)

    def read(self, index: int, subindex: int = 0) -> int:
        return self.sdo.read(index, subindex)

    def write(self, index: int, subindex: int, value: int) -> None:
        self.sdo.write(index, subindex, value)

    # --- process data -----------------------------------------------------------------------

    def map_process_data(self, outputs: Sequence[MappedObject],
                         inputs: Sequence[MappedObject]) -> None:
        """RPDOs event-driven (applied on arrival, so a command sent after sample k acts at
        SYNC k+1), TPDOs on every SYNC. SYNCs carry the counter byte where the drive counts
        them (0x1019), and then the drive's SYNC echo (0x2004), where it has one, closes the
        first TPDO."""
        counting = has(self.dictionary, objects.SYNC_COUNTER_OVERFLOW)
        if counting:
            self.write(objects.SYNC_COUNTER_OVERFLOW, 0, cia301.SYNC_COUNTER_MAX)
        echo_var = variable(self.dictionary, objects.SYNC_ECHO)
        echo = (mapped_object(echo_var) if counting and echo_var is not None
                and echo_var.pdo_mappable else None)
        rpdos = plan_pdos(self.dictionary, self.node_id, outputs, True, None, self.name)
        tpdos = plan_pdos(self.dictionary, self.node_id, inputs, False, echo, self.name)
        write_pdos(self.sdo, rpdos, True, cia301.TRANSMISSION_ASYNC)
        write_pdos(self.sdo, tpdos, False, cia301.TRANSMISSION_SYNC)
        self._plan = (rpdos, tpdos, counting)

    def start(self, period: float) -> None:
        """Cycle period, synchronous window and heartbeats by SDO, then NMT operational; the
        heartbeat consumer starts watching."""
        if self._plan is None:
            raise DriveError(f"{self.name}: start before map_process_data")
        rpdos, tpdos, counting = self._plan
        self.period = period
        period_us = int(round(period * 1e6))
        if has(self.dictionary, objects.CYCLE_PERIOD_US):
            self.write(objects.CYCLE_PERIOD_US, 0, period_us)
        window = None
        if has(self.dictionary, objects.SYNC_WINDOW_US):
            # the response timeout, for the reason in driver.canopen_cycle
            window = self.bus_cycle.response_timeout
            self.write(objects.SYNC_WINDOW_US, 0, int(round(window * 1e6)))
        heartbeat_ms = 0
        if has(self.dictionary, objects.PRODUCER_HEARTBEAT_MS):
            self.write(objects.PRODUCER_HEARTBEAT_MS, 0, self.heartbeat_ms)
            heartbeat_ms = self.heartbeat_ms
        self.health.start_producing(self.master_id)
        if has(self.dictionary, objects.CONSUMER_HEARTBEAT, 1):
            self.write(objects.CONSUMER_HEARTBEAT, 1,
                       self.master_id << cia301.HEARTBEAT_CONSUMER_NODE_SHIFT
                       | MASTER_HEARTBEAT_CONSUMER_MS)
        self.bus_cycle.configure(self.row, rpdos, tpdos, counting, window, period)
        try:
            self.node.nmt.state = "OPERATIONAL"
        except (can.CanError, OSError) as exc:
            raise DriveError(f"{self.name}: cannot send NMT: {exc}") from exc
        self.health.watch(heartbeat_ms, period)

    def send(self, outputs: Sequence[int]) -> None:
        try:
            self.bus_cycle.send(self.row, outputs)
        except (can.CanError, OSError) as exc:
            raise DriveError(f"{self.name}: cannot send RPDO: {exc}") from exc

    def exchange(self) -> tuple[int, ...]:
        """One cycle of the bus (its SYNC reaches every drive on it); this drive's inputs."""
        try:
            self.bus_cycle.exchange()
        except (can.CanError, OSError) as exc:
            raise DriveError(f"{self.name}: cannot send SYNC: {exc}") from exc
        return self.bus_cycle.inputs(self.row)

    @property
    def failure(self) -> DriveError | None:
        return self.bus_cycle.rows[self.row].failure

    @property
    def has_warnings(self) -> bool:
        return bool(self._warnings)

    @property
    def warning_lists(self) -> tuple[list[str], ...]:
        return (self._warnings,)

    def warnings(self) -> list[str]:
        if not self._warnings:
            return []
        out = self._warnings[:]
        del self._warnings[:len(out)]
        return out

    # --- shutdown ---------------------------------------------------------------------------

    def stop(self) -> None:
        """Tell the drive to stop watching us, leave operational, stop our heartbeat."""
        try:
            if has(self.dictionary, objects.CONSUMER_HEARTBEAT, 1):
                self.write(objects.CONSUMER_HEARTBEAT, 1, 0)
            self.node.nmt.state = "PRE-OPERATIONAL"
        except (DriveError, can.CanError, OSError, RuntimeError):
            pass  # best effort: the bus or the drive may be gone
        finally:
            self.health.close()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.health.close()
        self.bus_cycle.leave(self.row)
        if self.owns_network:
            self.network.disconnect()
