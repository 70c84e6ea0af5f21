"""The master side: a transport-neutral `Drive` interface and its CANopen (CiA 402) backend."""

from driver.interface import (
    CommandRangeError,
    Drive,
    DriveError,
    DriveFault,
    DriveLost,
    DriveTimeout,
    EncoderGlitch,
    Sample,
)

__all__ = ["CommandRangeError", "Drive", "DriveError", "DriveFault", "DriveLost", "DriveTimeout",
           "EncoderGlitch", "Sample"]
