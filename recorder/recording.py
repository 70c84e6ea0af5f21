"""A recording in memory: the contract's columns as arrays, plus metadata.

MCAP is the native format, CSV the interchange one (DESIGN.md: `t,q,current,joint_torque`,
optional extra columns, optional `# key=value` lines before the header). Both readers
(`csv_io`, `mcap_io`) return this class and raise this module's error, and `reader.load_recording`
picks between them, so every tool accepts both. This module imports neither reader.
"""

from dataclasses import dataclass, field

import numpy as np

from model.parameters import Payload

# Identification and model-gap filter at tens of Hz, so no tool here can use slower samples;
# the usual mistake it catches is time written in ms (1 kHz data then looks 1 s apart).
SLOWEST_SAMPLE_PERIOD = 0.1  # s


class RecordingError(ValueError):
    """A recording that cannot be used; the message names the file and what is wrong."""


@dataclass
class Recording:
    t: np.ndarray  # s
    q: np.ndarray  # rad
    current: np.ndarray  # A, measured motor current
    joint_torque: np.ndarray  # N.m, torque-sensor reading
    metadata: dict[str, str] = field(default_factory=dict)
    source: str = ""

    def __len__(self) -> int:
        return len(self.t)

    def payload(self) -> Payload | None:
        """The payload stored in the metadata, if any (`payload_mass`, `payload_position`)."""
        if "payload_mass" not in self.metadata:
            return None
        try:
            mass = float(self.metadata["payload_mass"])
            x, y = (float(v) for v in self.metadata.get("payload_position", "0,0").split(","))
            return Payload(mass, x, y)
        except ValueError as exc:
            raise RecordingError(f"{self.source}: metadata payload: {exc}") from None

    def check(self) -> "Recording":
        """Refuse what no tool can use: NaN, too short, time not increasing or not in
        seconds. A joint torque that is NaN throughout is a drive without a torque sensor (a
        standard CiA 402 drive has none): readable, refused only by the tools that need it
        (`with_joint_torque`)."""
        for name in ("t", "q", "current", "joint_torque"):
            column = getattr(self, name)
            if name == "joint_torque" and not np.any(np.isfinite(column)):
                continue
            if not np.all(np.isfinite(column)):
                row = int(np.argmin(np.isfinite(column)))
                raise RecordingError(f"{self.source}: column {name}: non-finite value at "
                                     f"sample {row}")
        if len(self.t) < 2:
            raise RecordingError(f"{self.source}: {len(self.t)} samples; a recording needs "
                                 "at least 2")
        if np.any(np.diff(self.t) <= 0):
            row = int(np.argmax(np.diff(self.t) <= 0)) + 1
            raise RecordingError(f"{self.source}: column t: time does not increase at "
                                 f"sample {row}")
        period = float(np.median(np.diff(self.t)))
        if period > SLOWEST_SAMPLE_PERIOD:
            raise RecordingError(f"{self.source}: column t: samples {period:g} apart; t is in "
                                 f"seconds and a recording is sampled every "
                                 f"{SLOWEST_SAMPLE_PERIOD:g} s or faster (time in ms?)")
        return self

    def with_joint_torque(self) -> "Recording":
        """This recording, refused with one line if it has no joint-torque readings."""
        if len(self.joint_torque) and not np.any(np.isfinite(self.joint_torque)):
            raise RecordingError(f"{self.source}: no joint-torque readings (recorded from a "
                                 "drive without a torque sensor); identification and "
                                 "model-gap need them")
        return self

