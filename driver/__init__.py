"""The master side: the `Drive` interface, the transport-neutral CiA 402 layer and its
transports (CANopen now; EtherCAT against `driver.transport`)."""

from driver.interface import (
    CommandRangeError,
    Drive,
    DriveError,
    DriveFault,
    DriveLost,
    DriveTimeout,
    EncoderGlitch,
    ForeignMaster,
    ProfileError,
    Sample,
)

__all__ = ["CommandRangeError", "Drive", "DriveError", "DriveFault", "DriveLost", "DriveTimeout",
           "EncoderGlitch", "ForeignMaster", "ProfileError", "Sample"]
