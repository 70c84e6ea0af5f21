"""The physical joint behind the virtual drive: the model integrated exactly, seen through
realistic sensors (19-bit encoder, noisy current and torque readings)."""

from dataclasses import dataclass

import numpy as np

from model import dynamics
from model.parameters import ActuatorParameters, Payload
from protocol import objects as od


@dataclass(frozen=True)
class SensorNoise:
    """Standard deviations of the drive's readings (assumed, typical of a 16-bit current ADC and
    a strain-gauge torque sensor; the paper does not publish them)."""

    current: float = 0.01  # A
    joint_torque: float = 0.05  # N.m
    seed: int | None = 0


@dataclass(frozen=True)
class Measurement:
    position_increments: int
    velocity_increments_per_s: int
    motor_current: float  # A, as read by the drive's current sensor
    joint_torque_reading: float  # N.m before the sensor gain K_j


class Plant:
    """True state of the joint with its payload; advances only when told to (lock-step)."""

    def __init__(self, parameters: ActuatorParameters, payload: Payload = Payload(),
                 noise: SensorNoise = SensorNoise(), initial_position: float | None = None):
        self.base_parameters = parameters
        self.noise = noise
        self._rng = np.random.default_rng(noise.seed)
        self.set_payload(payload)
        self.position = (dynamics.rest_position(self._packed) if initial_position is None
                         else initial_position)
        self.velocity = 0.0
        self.time = 0.0
        self._acceleration = 0.0
        self._dry = 0.0
        self._dry_level = parameters.dry_friction
        self._current = 0.0
        # load the compiled physics now, not in the first SYNC: a process's first call of
        # compiled code takes seconds, which a heartbeat watch would see as a dead drive
        dynamics.step(self.position, 0.0, 0.0, self._packed, 1e-3, dynamics.SUBSTEPS)
        self.joint_torque()

    def set_payload(self, payload: Payload) -> None:
        self.payload = payload
        self.parameters = self.base_parameters.with_payload(payload)
        self._packed = self.parameters.packed()

    def advance(self, current: float, dt: float) -> None:
        (self.position, self.velocity, self._acceleration, self._dry,
         self._dry_level) = dynamics.step(self.position, self.velocity, current, self._packed,
                                          dt, dynamics.SUBSTEPS)
        self._current = current
        self.time += dt

    def joint_torque(self) -> float:
        """What the link side transmits (the inverse dynamics' joint side) in the last substep:
        sliding, the joint carries its own Coulomb part (Fsj); stuck, its share of the holding
        friction (the direction is the share of the level in use). The effects sit in the
        transmission, on the motor side of the sensor, so the sensor does not see them."""
        direction = self._dry / self._dry_level if self._dry_level > 0 else 0.0
        _, joint = dynamics.sample_inverse_dynamics(self.position, self.velocity,
                                                    self._acceleration, direction, self._packed)
        return float(joint)

    def measure(self) -> Measurement:
        current = self._current + self._rng.normal(0.0, self.noise.current)
        reading = (self.joint_torque() / self.parameters.torque_sensor_gain
                   + self._rng.normal(0.0, self.noise.joint_torque))
        return Measurement(
            position_increments=od.position_to_increments(self.position),
            velocity_increments_per_s=od.position_to_increments(self.velocity),
            motor_current=float(current),
            joint_torque_reading=float(reading),
        )
