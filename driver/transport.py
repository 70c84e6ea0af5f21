"""The seam between the transport-neutral CiA 402 layer (`driver.cia402_drive`) and a fieldbus.

A CiA 402 drive is the same object dictionary whatever carries it; what differs is how objects
are reached. Both buses offer the same two services, and this contract is exactly those two:

- **Acyclic access** (`read`, `write`): CANopen SDO; EtherCAT CoE mailbox SDO. Used for
  configuration, for steering the CiA 402 state machine, for reading scaling objects.
- **Cyclic process data** (`map_process_data`, `send`, `exchange`): the master stages its
  outputs, then one exchange triggers the cycle and returns the inputs sampled in it.
  CANopen: `send` transmits the RPDO(s) at once, `exchange` sends a SYNC and collects the
  TPDOs that answer it. EtherCAT: `send` writes the output image, `exchange` sends the one
  frame that carries it and returns the input image, checking the working counter.

Timing contract, identical on both buses: outputs given by `send` after the inputs of cycle k
are applied by the drive at cycle k+1 (latched on SYNC k+1 / at the frame of cycle k+1), and
the inputs returned by `exchange` for cycle k+1 are the drive's state after applying them.
That is what makes a lock-step simulation advance exactly one period per `exchange`.

Values cross the seam as plain integers in the objects' own units (increments, mA, per mille,
...): unit scaling belongs to the CiA 402 layer, which reads the scaling objects through
`read`. Process data is positional: `exchange` returns one integer per object of the `inputs`
passed to `map_process_data`, in that order, however the transport split them into frames
(several TPDOs of at most 8 bytes; one TxPDO). Positional tuples instead of dicts keep the
per-cycle cost to one unpack per frame.

Failures use `driver.interface`'s hierarchy so the layers above never see a bus exception:
`DriveTimeout` (the cycle's inputs did not come: missing TPDO, short working counter),
`DriveLost` (heartbeat missing, reboot, slave left OP), `DriveError` (an acyclic access was
refused or unanswered; the message names the object), `ProfileError` (the device cannot carry
the requested process data, before anything was enabled), `ForeignMaster` (another master
drives the device). Emergencies (CANopen EMCY, EtherCAT CoE emergency) carry CiA 301 error
codes on both buses; the transport hands them to `on_emergency` from its receive context.

Time: a transport's watchdogs measure time on the clock it is given (`driver.clock`): drive
time in lock-step (advanced by the cycles the bus runs), so a slow or busy host cannot trip
one, the wall clock in real time; one code path either way. See `driver.canopen_health` for
why that is sound for the heartbeat consumer.
"""

from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence

from canopen.objectdictionary import ObjectDictionary

from driver.interface import DriveError
from protocol.pdo import MappedObject

EmergencyHandler = Callable[[int, int], None]  # (CiA 301 error code, error register)


class Transport(ABC):
    """A master's link to one CiA 402 device on one fieldbus."""

    name: str  # how messages name the device: "node 2", "slave 1"
    dictionary: ObjectDictionary  # the objects the device declares (its EDS, or its ESI's CoE)
    on_emergency: EmergencyHandler = staticmethod(lambda code, register: None)

    @abstractmethod
    def boot(self, timeout: float) -> None:
        """Bring the device's communication up to where acyclic access works and process data
        can be mapped (CANopen: NMT reset communication, boot-up, pre-operational; EtherCAT:
        INIT -> PRE-OP). Raises ForeignMaster, before resetting anything, if another master is
        driving the device; DriveLost if it does not answer within `timeout` s."""

    @abstractmethod
    def read(self, index: int, subindex: int = 0) -> int:
        """Acyclic read of one object (SDO / CoE upload), decoded with its dictionary type."""

    @abstractmethod
    def write(self, index: int, subindex: int, value: int) -> None:
        """Acyclic write of one object (SDO / CoE download). Writing an object that is also
        mapped as a cyclic output must take effect too (a drive in EtherCAT OP takes the
        controlword from the process data, so the transport also updates its output image)."""

    @abstractmethod
    def map_process_data(self, outputs: Sequence[MappedObject],
                         inputs: Sequence[MappedObject]) -> None:
        """Configure the cyclic data within what the device's dictionary allows, write it by
        acyclic access and read it back. Raises ProfileError naming what cannot be mapped."""

    @abstractmethod
    def start(self, period: float) -> None:
        """Enter cyclic operation at `period` s (CANopen: 0x1006, heartbeats, NMT operational;
        EtherCAT: DC cycle, SAFE-OP -> OP). The drive sees zero outputs until `send`."""

    @abstractmethod
    def send(self, outputs: Sequence[int]) -> None:
        """Stage one value per mapped output object, applied by the drive at the next cycle."""

    @abstractmethod
    def exchange(self) -> tuple[int, ...]:
        """Run one cycle and return one value per mapped input object, sampled in this cycle
        (never an earlier cycle's value). Raises `failure` if set, else DriveTimeout."""

    @property
    @abstractmethod
    def failure(self) -> DriveError | None:
        """What ended the link, if anything (lost, rebooted, timed out); sticky until boot."""

    def warnings(self) -> list[str]:
        """Bus-level problems since the last call that did not end the link (a duplicate or
        late frame, an overloaded bus)."""
        return []

    @property
    def has_warnings(self) -> bool:
        """Whether `warnings()` has anything to say."""
        return False

    @property
    def warning_lists(self) -> tuple[list[str], ...]:
        """The lists `warnings()` drains, each cleared in place (none here)."""
        return ()

    @abstractmethod
    def stop(self) -> None:
        """Leave cyclic operation (CANopen: NMT pre-operational; EtherCAT: PRE-OP). Best
        effort: never raises."""

    @abstractmethod
    def close(self) -> None:
        """Release the bus. Idempotent."""
