"""The physical joint behind the virtual drive: the model integrated exactly, with a holding
brake, seen through realistic sensors (noisy current and torque readings; the encoder's
quantisation is the drive's unit conversion, `sim_bus.device`)."""

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from model import dynamics
from model.parameters import ActuatorParameters, Payload

# assumed: above the motor's rated torque (30 N.m, 0x6076) as holding brakes are sized, and
# above the 25 N.m the paper's heaviest payload (30 kg at 5 cm) hangs on the joint
BRAKE_HOLDING_TORQUE = 40.0  # N.m
NOISE_BATCH = 4096  # sensor-noise draws per numpy call


@dataclass(frozen=True)
class SensorNoise:
    """Standard deviations of the drive's readings (assumed, typical of a 16-bit current ADC and
    a strain-gauge torque sensor; the paper does not publish them)."""

    current: float = 0.01  # A
    joint_torque: float = 0.05  # N.m
    seed: int | None = 0


class Measurement(NamedTuple):
    """One cycle's sensor readings (a named tuple: one is made per cycle)."""

    position: float  # rad, the encoder's shaft (the drive quantises it)
    velocity: float  # rad/s
    motor_current: float  # A, as read by the drive's current sensor
    joint_torque_reading: float  # N.m before the sensor gain K_j


class Plant:
    """True state of the joint with its payload; advances only when told to (lock-step).

    The holding brake acts in the transmission like dry friction: engaged, it adds its holding
    torque to the dry-friction level of the model's own stick-slip integrator, so a joint at
    rest stays put while gravity needs less than that, and a moving one is stopped by it.
    """

    def __init__(self, parameters: ActuatorParameters, payload: Payload = Payload(),
                 noise: SensorNoise = SensorNoise(), initial_position: float | None = None):
        self.base_parameters = parameters
        self.noise = noise
        self._rng = np.random.default_rng(noise.seed)
        self._draws: list[float] = []
        self._next_draw = 0
        self.time = 0.0  # s since power-on
        self.set_payload(payload)
        self.position = (dynamics.rest_position(self._packed) if initial_position is None
                         else initial_position)
        self.velocity = 0.0
        self._dry = 0.0
        self._dry_level = parameters.dry_friction
        self._current = 0.0
        # at rest, before the first period (a drive samples its sensors at power-on)
        self._joint_torque = float(dynamics.inverse_dynamics(self.position, 0.0, 0.0, 0.0,
                                                             self._packed)[1])

    def set_payload(self, payload: Payload) -> None:
        self.payload = payload
        self.parameters = self.base_parameters.with_payload(payload)
        self._packed_start = self.parameters.packed()
        self._drifts = dynamics.drifts(self._packed_start)
        self._set_packed(self.time)

    def _set_packed(self, elapsed: float) -> None:
        """The parameters at `elapsed` s since power-on (effects that drift over time, such
        as warm-up friction, change them), without and with the brake."""
        self._packed = dynamics.at_elapsed(self._packed_start, elapsed)
        self._packed_braked = self._packed.copy()
        self._packed_braked[dynamics.P_DRY] += BRAKE_HOLDING_TORQUE

    def warm_up(self) -> None:
        """Compile (or load) the integrator now, on a throwaway state: the first SYNC must be
        answered within one period, not after a 0.3-0.5 s compilation (seconds on a busy
        host, far longer than a master waits for its first sample). The results are unused."""
        dynamics.step_sensed(self.position, 0.0, 0.0, self._packed, self._packed, 1e-3,
                             dynamics.SUBSTEPS)

    def advance(self, current: float, dt: float, braked: bool = False) -> None:
        """One period under `current`. The holding brake sits in the transmission with the
        other effects, on the motor side of the torque sensor: the joint torque is the
        unbraked inverse dynamics' joint side, so the sensor does not see the brake."""
        if self._drifts:
            self._set_packed(self.time)
        (self.position, self.velocity, self._dry, self._dry_level,
         self._joint_torque) = dynamics.step_sensed(
            self.position, self.velocity, current,
            self._packed_braked if braked else self._packed, self._packed, dt,
            dynamics.SUBSTEPS)
        self._current = current
        self.time += dt

    def _standard_normal(self) -> float:
        """The generator's next N(0, 1) draw, taken in batches (one numpy call per draw cost
        more than the rest of a measurement); the sequence is the one scalar draws give."""
        if self._next_draw == len(self._draws):
            self._draws = self._rng.standard_normal(NOISE_BATCH).tolist()
            self._next_draw = 0
        self._next_draw += 1
        return self._draws[self._next_draw - 1]

    def measure(self) -> Measurement:
        current = self._current + self.noise.current * self._standard_normal()
        reading = (self._joint_torque / self.parameters.torque_sensor_gain
                   + self.noise.joint_torque * self._standard_normal())
        return Measurement(self.position, self.velocity, current, reading)
