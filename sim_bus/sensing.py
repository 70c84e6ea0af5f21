"""A virtual drive's period in compiled code: the plant advanced one period and its sensors
read into the dictionary's units, in one call. One home for what a drive's cycle repeats every
period, shared by `Cia402Device.cycle` (one drive) and `sim_bus.line_physics` (a line's batch):
in Python it cost about ten calls and a dozen small objects a period.

A drive's terms are a row of floats (the T_* columns), its readings' ranges a (6, 2) integer
array and the readings a row of six integers, in `sim_bus.device.LIVE_READINGS` order:
position, velocity, motor current, joint torque sensor, current actual and torque actual (the
last two per mille of the rated value, left as they are where the drive has no rating).
"""

import numba
import numpy as np

from model import dynamics
from protocol import objects

# columns of a plant's state row (`sim_bus.plant.Plant.state`): what one period changes
POSITION, VELOCITY, DRY, DRY_LEVEL, JOINT_TORQUE, CURRENT, TIME = range(7)
STATE_SIZE = 7
# columns of a drive's float terms
(T_PERIOD, T_MAX_CURRENT, T_TRIP, T_WINDOW_LOW, T_WINDOW_HIGH, T_PER_RAD, T_RATED_CURRENT,
 T_RATED_TORQUE, T_DRIVE_GAIN, T_SENSOR_GAIN, T_NOISE_CURRENT, T_NOISE_TORQUE) = range(12)
N_TERMS = 12
N_READINGS = 6
_MILLI = objects.MILLI


@numba.njit(cache=True, error_model="numpy")
def saturate(value: float, low: int, high: int) -> int:
    """A reading as its object holds it, as a sensor's converter saturates: NaN and below the
    range give its low end, above it its high end, else the nearest integer (half to even,
    as Python's round())."""
    if not value > low:
        return low
    if not value < high:
        return high
    return np.int64(np.rint(value))


@numba.njit(cache=True, error_model="numpy")
def sense(q: float, qd: float, current: float, joint: float, noise_current: float,
          noise_torque: float, terms: np.ndarray, ranges: np.ndarray,
          readings: np.ndarray) -> None:
    """The sensors' reading of the joint at (q, qd) under `current` with joint torque
    `joint`, `noise_*` N(0, 1) draws, into `readings`."""
    measured = current + terms[T_NOISE_CURRENT] * noise_current
    reading = joint / terms[T_SENSOR_GAIN] + terms[T_NOISE_TORQUE] * noise_torque
    per_rad = terms[T_PER_RAD]
    readings[0] = saturate(q * per_rad, ranges[0, 0], ranges[0, 1])
    readings[1] = saturate(qd * per_rad, ranges[1, 0], ranges[1, 1])
    readings[2] = saturate(measured * _MILLI, ranges[2, 0], ranges[2, 1])
    readings[3] = saturate(reading * _MILLI, ranges[3, 0], ranges[3, 1])
    if terms[T_RATED_CURRENT] > 0:
        readings[4] = saturate(measured / terms[T_RATED_CURRENT] * _MILLI, ranges[4, 0],
                               ranges[4, 1])
    if terms[T_RATED_TORQUE] > 0:
        readings[5] = saturate(terms[T_DRIVE_GAIN] * measured / terms[T_RATED_TORQUE] * _MILLI,
                               ranges[5, 0], ranges[5, 1])


@numba.njit(cache=True, error_model="numpy")
def sample(state: np.ndarray, draws: np.ndarray, cursor: np.ndarray, terms: np.ndarray,
           ranges: np.ndarray, readings: np.ndarray) -> None:
    """The sensors' reading of the plant's `state` as it is (at power-on, after a reset),
    two noise draws taken at `cursor` (the caller renews them first)."""
    k = cursor[0]
    cursor[0] = k + 2
    sense(state[POSITION], state[VELOCITY], state[CURRENT], state[JOINT_TORQUE], draws[k],
          draws[k + 1], terms, ranges, readings)


@numba.njit(cache=True, error_model="numpy")
def advance_and_sample(state: np.ndarray, current: float, p_motion: np.ndarray,
                       p: np.ndarray, substeps: int, draws: np.ndarray, cursor: np.ndarray,
                       terms: np.ndarray, ranges: np.ndarray, readings: np.ndarray) -> float:
    """One period (terms[T_PERIOD]) of the plant under `current` (`Plant.advance`: its motion
    under `p_motion`, the joint torque under `p`), then its sensors read (`sample`). Returns
    the new position (rad)."""
    dt = terms[T_PERIOD]
    q, qd, dry, level, joint = dynamics.step_sensed(state[POSITION], state[VELOCITY], current,
                                                    p_motion, p, dt, substeps)
    state[POSITION], state[VELOCITY], state[DRY], state[DRY_LEVEL] = q, qd, dry, level
    state[JOINT_TORQUE] = joint
    state[CURRENT] = current
    state[TIME] += dt
    sample(state, draws, cursor, terms, ranges, readings)
    return q
