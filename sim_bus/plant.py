"""The physical joint behind the virtual drive: the model integrated exactly, with a holding
brake, seen through realistic sensors (noisy current and torque readings; the encoder's
quantisation is the drive's unit conversion, `sim_bus.device`)."""

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from model import dynamics
from model.parameters import ActuatorParameters, Payload
from sim_bus import sensing
from sim_bus.sensing import (  # noqa: F401 (the state's columns, as a line's rows use them)
    CURRENT,
    DRY,
    DRY_LEVEL,
    JOINT_TORQUE,
    POSITION,
    STATE_SIZE,
    TIME,
    VELOCITY,
)

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




class Plant:
    """True state of the joint with its payload; advances only when told to (lock-step).

    The holding brake acts in the transmission like dry friction: engaged, it adds its holding
    torque to the dry-friction level of the model's own stick-slip integrator, so a joint at
    rest stays put while gravity needs less than that, and a moving one is stopped by it.

    The state, the parameters and the sensor-noise draws live in rows of arrays (its own until
    `adopt`): a line of drives (`sim_bus.line_physics`) advances all its plants in one
    compiled call over those rows, and each plant still reads and advances its own.
    """

    def __init__(self, parameters: ActuatorParameters, payload: Payload = Payload(),
                 noise: SensorNoise = SensorNoise(), initial_position: float | None = None):
        self.base_parameters = parameters
        self.noise = noise
        self._rng = np.random.default_rng(noise.seed)
        self.state = np.zeros(STATE_SIZE)
        packed = parameters.packed()
        self._packed, self._packed_braked = np.zeros_like(packed), np.zeros_like(packed)
        # the noise draws and the index of the next one (a one-element array: a line's row)
        self.draws = np.zeros(NOISE_BATCH)
        self.cursor = np.full(1, NOISE_BATCH, dtype=np.int64)  # empty: drawn at first use
        self.revision = 0  # counts parameter changes (a line re-reads what derives from them)
        self.on_change: Callable[[], None] | None = None  # told of each (a line's)
        self.set_payload(payload)
        self.state[POSITION] = (dynamics.rest_position(self._packed) if initial_position
                                is None else initial_position)
        self.state[DRY_LEVEL] = parameters.dry_friction
        # at rest, before the first period (a drive samples its sensors at power-on)
        self.state[JOINT_TORQUE] = dynamics.inverse_dynamics(self.position, 0.0, 0.0, 0.0,
                                                              self._packed)[1]

    @property
    def position(self) -> float:
        """rad."""
        return float(self.state[POSITION])

    @property
    def velocity(self) -> float:
        """rad/s."""
        return float(self.state[VELOCITY])

    @property
    def time(self) -> float:
        """s since power-on (its periods)."""
        return float(self.state[TIME])

    @property
    def drifts(self) -> bool:
        """Whether its parameters change with elapsed time (renewed before each period)."""
        return self._drifts

    def adopt(self, state: np.ndarray, packed: np.ndarray, packed_braked: np.ndarray,
              draws: np.ndarray, cursor: np.ndarray) -> None:
        """Move the state, the parameters and the noise draws into these rows (a line's,
        views of its arrays), values kept: from now on they live there."""
        for row, mine in ((state, self.state), (packed, self._packed),
                          (packed_braked, self._packed_braked), (draws, self.draws),
                          (cursor, self.cursor)):
            row[...] = mine
        self.state, self._packed, self._packed_braked = state, packed, packed_braked
        self.draws, self.cursor = draws, cursor

    def set_payload(self, payload: Payload) -> None:
        self.payload = payload
        self.parameters = self.base_parameters.with_payload(payload)
        self._packed_start = self.parameters.packed()
        self._drifts = dynamics.drifts(self._packed_start)
        self._set_packed(self.time)
        self.revision += 1
        if self.on_change is not None:
            self.on_change()

    def _set_packed(self, elapsed: float) -> None:
        """The parameters at `elapsed` s since power-on (effects that drift over time, such
        as warm-up friction, change them), without and with the brake, in place."""
        self._packed[:] = dynamics.at_elapsed(self._packed_start, elapsed)
        self._packed_braked[:] = self._packed
        self._packed_braked[dynamics.P_DRY] += BRAKE_HOLDING_TORQUE

    def renew_parameters(self) -> None:
        """The drifting parameters at this time: what `advance` does first when they drift
        (a line calls it for its drifting plants before advancing them together)."""
        self._set_packed(self.time)

    def warm_up(self) -> None:
        """Compile (or load) the integrator now, on a throwaway state: the first SYNC must be
        answered within one period, not after a 0.3-0.5 s compilation (seconds on a busy
        host, far longer than a master waits for its first sample). The results are unused."""
        terms = np.zeros(sensing.N_TERMS)
        terms[sensing.T_PERIOD] = 1e-3
        sensing.advance_and_sample(self.state.copy(), 0.0, self._packed, self._packed,
                                   dynamics.SUBSTEPS, np.zeros(2), np.zeros(1, dtype=np.int64),
                                   terms, np.zeros((sensing.N_READINGS, 2), dtype=np.int64),
                                   np.zeros(sensing.N_READINGS, dtype=np.int64))

    def advance(self, current: float, dt: float, braked: bool = False) -> None:
        """One period `dt` under `current`, the sensors not read (`advance_sampled` is a
        drive's period). The holding brake sits in the transmission with the other effects,
        on the motor side of the torque sensor: the joint torque is the unbraked inverse
        dynamics' joint side, so the sensor does not see the brake."""
        x = self.state
        if self._drifts:
            self._set_packed(float(x[TIME]))
        x[POSITION], x[VELOCITY], x[DRY], x[DRY_LEVEL], x[JOINT_TORQUE] = (
            dynamics.step_sensed(x[POSITION], x[VELOCITY], current,
                                 self._packed_braked if braked else self._packed,
                                 self._packed, dt, dynamics.SUBSTEPS))
        x[CURRENT] = current
        x[TIME] += dt

    def advance_sampled(self, current: float, braked: bool, terms: np.ndarray,
                        ranges: np.ndarray, readings: np.ndarray) -> float:
        """A drive's period: `advance` by terms[T_PERIOD], then the sensors' reading into
        `readings` (`sim_bus.sensing`: the drive's `terms` and its readings' `ranges`), in
        one compiled call. Returns the new position (rad)."""
        if self._drifts:
            self._set_packed(float(self.state[TIME]))
        if self.cursor[0] > NOISE_BATCH - 2:
            self.refill_draws()
        return sensing.advance_and_sample(
            self.state, current, self._packed_braked if braked else self._packed,
            self._packed, dynamics.SUBSTEPS, self.draws, self.cursor, terms, ranges, readings)

    def sample(self, terms: np.ndarray, ranges: np.ndarray, readings: np.ndarray) -> None:
        """The sensors' reading of the joint as it is (at power-on, after a reset), into
        `readings` (as `advance`)."""
        if self.cursor[0] > NOISE_BATCH - 2:
            self.refill_draws()
        sensing.sample(self.state, self.draws, self.cursor, terms, ranges, readings)

    def refill_draws(self) -> None:
        """The draws not used yet moved to the front and the rest of the batch drawn from the
        generator (one numpy call per draw cost more than the rest of a measurement): the
        sequence is the one scalar draws give however early this is called (the generator
        fills in order, in chunks or not), so a line renews its drives' draws a few at a
        time (`DriveLine.renew_draws`) instead of all of them in the cycle that empties them."""
        used = int(self.cursor[0])
        rest = NOISE_BATCH - used
        if rest:
            self.draws[:rest] = self.draws[used:].copy()
        self._rng.standard_normal(out=self.draws[rest:])
        self.cursor[0] = 0
