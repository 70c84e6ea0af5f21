"""Identification of the actuator model from two experiments (the paper's section II-B).

The inverse dynamics are linear in the parameters. Written as homogeneous equations, one row
per sample for the motor side and one for the torque sensor,

    motor:  I_m qdd + I_j qdd + MY g sin q + MX g cos q + (Fvm + Fvj) qd + (Fsm + Fsj) sgn qd
            + off_m + off_j - RK_m i + tau_payload = 0
    sensor: I_j qdd + MY g sin q + MX g cos q + Fvj qd + Fsj sgn qd + off_j - K_j tau_s
            + tau_payload = 0

and stacked over an experiment without and one with a known payload, they form M [chi; 1] = 0,
the last column being the payload's known torque. Total least squares takes the closest rank-
deficient M (SVD, last right singular vector) and the payload column fixes the scale: drive
gain, sensor gain, inertias, first moments, friction and offsets come out at once.

Signal processing, and why it differs from the paper's: velocity and acceleration by centred
differences of the measured position; then every column (regressors, current, torque) goes
through the same zero-phase Butterworth low-pass, so the filter acts on both sides of the
linear equation alike and cannot bias the fit. The paper's 5 Hz filter smears the friction
reversal at qd = 0 over ~0.2 s; at 25 Hz (default) the reversal survives and, with samples
below 0.05 rad/s dropped, dry friction is not mistaken for something else. Decimation to 100 Hz
after filtering keeps the rows nearly independent for the statistics.

Drive-side effects already named (a torque constant that saturates, found by model-gap) are
used when given: the current column becomes the current that makes torque, i - L(i), taken on
the raw samples before filtering (the loss is nonlinear). Their parameters are per ampere, so
they do not depend on the drive gain being identified. Transmission effects are not fitted
here: model-gap refits friction with them.
"""

import math
from dataclasses import dataclass, replace

import numpy as np

from model import dynamics
from model.defaults import CUTOFF_HZ
from model.dynamics import inverse_dynamics
from model.effects import EFFECTS, Effects
from model.parameters import ActuatorParameters, Payload

# the inverse dynamics' parameters, then the two measurement gains (current, torque sensor)
PARAMETERS = ("motor_inertia", "link_inertia", "first_moment_y", "first_moment_x",
              "viscous_friction_motor", "viscous_friction_joint", "dry_friction_motor",
              "dry_friction_joint", "torque_offset_motor", "torque_offset_joint", "drive_gain",
              "torque_sensor_gain")
FILTER_ORDER = 4
DECIMATE_TO_HZ = 100.0
MIN_SPEED = 0.05  # rad/s: slower samples say nothing clean about dry friction
EDGE = 0.2  # s dropped at both ends (filter transients)
MIN_DURATION = 2.0  # s
MIN_RANGE = 0.5  # rad of motion needed to separate the gravity terms
MAX_CONDITION = 1e4  # of the column-normalised regressor
MAX_SCALE_STD = 10.0  # % relative std of the drive gain: above, the payload did not fix the scale
SAME_POSITION = 1e-3  # rad RMS: two recordings this close in position ...
SAME_CURRENT = 0.02  # ... and within 2 % in current are one experiment recorded twice


class IdentificationError(ValueError):
    """The data cannot identify the model; the message says why (and the condition number
    when the regressor is the problem)."""


@dataclass(frozen=True)
class Experiment:
    t: np.ndarray
    q: np.ndarray
    current: np.ndarray
    joint_torque: np.ndarray
    payload: Payload
    name: str = ""


@dataclass(frozen=True)
class Identified:
    parameters: ActuatorParameters
    relative_std: dict[str, float]  # %
    std: dict[str, float]
    condition_number: float
    rmsd_motor: float  # N.m
    rmsd_joint: float  # N.m
    rows: int
    fits: dict  # per experiment: time, measured and predicted motor and joint torque


@dataclass(frozen=True)
class Columns:
    """Filtered, decimated signals of one experiment (the rows it contributes)."""

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    friction_sign: np.ndarray
    current: np.ndarray
    joint_torque: np.ndarray


def prepare(experiment: Experiment, cutoff_hz: float = CUTOFF_HZ) -> Columns:
    t = np.asarray(experiment.t, float)
    if t[-1] - t[0] < MIN_DURATION:
        raise IdentificationError(f"{experiment.name}: {t[-1] - t[0]:.2f} s of data; need at "
                                  f"least {MIN_DURATION} s")
    dt = float(np.median(np.diff(t)))
    if np.max(np.abs(np.diff(t) - dt)) > 0.5 * dt:
        raise IdentificationError(f"{experiment.name}: samples are not evenly spaced "
                                  f"(period {dt * 1e3:.3f} ms with gaps)")
    q = np.asarray(experiment.q, float)
    if np.ptp(q) < MIN_RANGE:
        raise IdentificationError(f"{experiment.name}: the joint moved over {np.ptp(q):.3f} rad;"
                                  f" nothing is excited (need {MIN_RANGE} rad or more)")
    rate = 1.0 / dt
    if cutoff_hz >= 0.5 * rate:
        raise IdentificationError(f"cutoff {cutoff_hz} Hz is above Nyquist for {rate:.0f} Hz")
    # imported here, once the data passed its checks: scipy.signal takes about 1 s to import
    # (it loads scipy.stats and more), which a refused recording's one line should not wait for
    from scipy import signal

    sos = signal.butter(FILTER_ORDER, cutoff_hz, fs=rate, output="sos")
    qd = np.gradient(q, dt)
    qdd = np.gradient(qd, dt)

    def smooth(x: np.ndarray) -> np.ndarray:
        return signal.sosfiltfilt(sos, x)

    qd_smooth = smooth(qd)
    step = max(1, int(round(rate / DECIMATE_TO_HZ)))
    keep = slice(int(EDGE * rate), len(t) - int(EDGE * rate), step)
    return Columns(t=t[keep], q=smooth(q)[keep], qd=qd_smooth[keep], qdd=smooth(qdd)[keep],
                   friction_sign=smooth(np.sign(qd_smooth))[keep],
                   current=smooth(np.asarray(experiment.current, float))[keep],
                   joint_torque=smooth(np.asarray(experiment.joint_torque, float))[keep])


def rows(columns: Columns, payload: Payload) -> tuple[np.ndarray, np.ndarray]:
    """Motor and sensor rows [unknown columns (12) | known payload torque] of one experiment,
    restricted to samples moving faster than MIN_SPEED. The inverse dynamics are linear in the
    model's parameters, so each column is the model's own torque for a unit value of one
    parameter (all others zero); the known column is the payload's alone."""
    moving = np.abs(columns.qd) > MIN_SPEED
    c = Columns(*(getattr(columns, f)[moving] for f in Columns.__dataclass_fields__))

    def torques(parameters: ActuatorParameters) -> tuple[np.ndarray, np.ndarray]:
        return inverse_dynamics(c.q, c.qd, c.qdd, c.friction_sign, parameters.packed())

    nothing = ActuatorParameters(**dict.fromkeys(PARAMETERS, 0.0))
    unit = [torques(replace(nothing, **{name: 1.0})) for name in PARAMETERS[:-2]]
    known_motor, known_joint = torques(nothing.with_payload(payload))
    zero = np.zeros(len(c.t))
    motor = np.column_stack([m for m, _ in unit] + [-c.current, zero, known_motor])
    sensor = np.column_stack([j for _, j in unit] + [zero, -c.joint_torque, known_joint])
    return motor, sensor


def _describe(payload: Payload) -> str:
    if payload.mass <= 0:
        return "no payload"
    return f"{payload.mass:g} kg at ({payload.x:g}, {payload.y:g}) m"


def _refuse_one_experiment(no_load: Experiment, load: Experiment) -> None:
    """The scale comes from the payload's difference between the experiments: the same payload
    twice, a payload that adds no torque, or the same data under two payload claims cannot
    give it."""
    if no_load.payload == load.payload:
        raise IdentificationError(
            f"{no_load.name} and {load.name} carry the same payload ({_describe(load.payload)})"
            ": one experiment twice cannot fix the scale; record LOAD with another payload")
    p = load.payload
    if p.mass * math.hypot(p.x, p.y) == 0:
        raise IdentificationError(f"{load.name}: the payload ({_describe(p)}) adds no torque "
                                  "at the joint (it sits on the axis); it cannot fix the scale")
    a, b = (np.asarray(e.q, float) for e in (no_load, load))
    i, j = (np.asarray(e.current, float) for e in (no_load, load))
    n = min(len(a), len(b))
    if (abs(len(a) - len(b)) <= 0.01 * max(len(a), len(b))
            and np.sqrt(np.mean((a[:n] - b[:n]) ** 2)) < SAME_POSITION
            and np.sqrt(np.mean((i[:n] - j[:n]) ** 2))
            < SAME_CURRENT * np.sqrt(np.mean(i[:n] ** 2))):
        raise IdentificationError(
            f"{no_load.name} and {load.name} are the same experiment (positions and currents "
            f"agree) yet are said to carry {_describe(no_load.payload)} and "
            f"{_describe(load.payload)}: record LOAD with the payload on the link")


def drive_side(effects: Effects) -> Effects:
    """The drive-side effects among `effects` (those identification uses)."""
    return Effects({name: effects.section(name) for name in effects.enabled()
                    if EFFECTS[name].side == "drive"})


def _torque_making_current(experiment: Experiment, drive: Effects) -> Experiment:
    """The experiment with its current replaced by the part that makes torque, i - L(i)."""
    unit_gain = ActuatorParameters(**{**dict.fromkeys(PARAMETERS, 0.0), "drive_gain": 1.0},
                                   effects=drive)
    p = unit_gain.packed()
    return replace(experiment, current=dynamics.motor_torque(
        np.asarray(experiment.current, float), p))


def identify(no_load: Experiment, load: Experiment, cutoff_hz: float = CUTOFF_HZ,
             effects: Effects | None = None) -> Identified:
    """The paper's total least squares over the two experiments, with the drive-side effects
    among `effects` applied to the currents (and carried by the result); IdentificationError
    when they cannot identify the model (why, in one line)."""
    drive = drive_side(effects or Effects())
    if drive.enabled():
        no_load, load = (_torque_making_current(e, drive) for e in (no_load, load))
    if load.payload.mass <= 0:
        raise IdentificationError(f"{load.name}: the load experiment carries no payload; the "
                                  "scale of the parameters cannot be identified without one")
    _refuse_one_experiment(no_load, load)
    prepared = [(prepare(e, cutoff_hz), e) for e in (no_load, load)]
    blocks = [rows(columns, e.payload) for columns, e in prepared]
    M = np.vstack([block for pair in blocks for block in pair])
    W = M[:, :-1]
    scale = np.linalg.norm(W, axis=0)
    if np.any(scale == 0):
        missing = [PARAMETERS[i] for i in np.flatnonzero(scale == 0)]
        raise IdentificationError(f"nothing in the data excites {', '.join(missing)}")
    condition = float(np.linalg.cond(W / scale))
    if not condition < MAX_CONDITION:
        raise IdentificationError(
            f"regressor is ill-conditioned (condition number {condition:.3g} > "
            f"{MAX_CONDITION:g}): the trajectory does not excite every parameter")
    _, singular, vt = np.linalg.svd(M, full_matrices=False)
    v = vt[-1]
    if abs(v[-1]) < 1e-12:
        raise IdentificationError("the payload column does not fix the scale (singular "
                                  "vector without a payload part)")
    chi = v[:-1] / v[-1]
    residual = M @ np.append(chi, 1.0)
    dof = M.shape[0] - len(chi)
    sigma2 = float(residual @ residual) / dof
    covariance = sigma2 * np.linalg.inv(W.T @ W)
    std = np.sqrt(np.diag(covariance))
    values = dict(zip(PARAMETERS, chi, strict=True))
    parameters = ActuatorParameters(**values, effects=drive)
    relative = {name: 100.0 * s / abs(values[name]) if values[name] != 0 else math.inf
                for name, s in zip(PARAMETERS, std, strict=True)}
    unphysical = [f"{name} {values[name]:.4g}" for name in
                  ("drive_gain", "torque_sensor_gain", "motor_inertia", "link_inertia")
                  if values[name] <= 0]
    if unphysical or relative["drive_gain"] > MAX_SCALE_STD:
        raise IdentificationError(
            f"the payload difference between {no_load.name} ({_describe(no_load.payload)}) and "
            f"{load.name} ({_describe(load.payload)}) cannot scale the solution: "
            + (", ".join(unphysical) + " (must be > 0)" if unphysical else
               f"drive_gain known only to {relative['drive_gain']:.0f} % "
               f"(need {MAX_SCALE_STD:g} %)"))

    fits = {}
    motor_err, joint_err = [], []
    for (columns, experiment), (motor, sensor) in zip(prepared, blocks, strict=True):
        # measured torque vs what the identified model predicts from the motion
        measured_motor = parameters.drive_gain * -motor[:, 10]
        predicted_motor = measured_motor + motor @ np.append(chi, 1.0)
        measured_joint = parameters.torque_sensor_gain * -sensor[:, 11]
        predicted_joint = measured_joint + sensor @ np.append(chi, 1.0)
        moving = np.abs(columns.qd) > MIN_SPEED
        fits[experiment.name] = {"t": columns.t[moving], "measured_motor": measured_motor,
                                 "predicted_motor": predicted_motor,
                                 "measured_joint": measured_joint,
                                 "predicted_joint": predicted_joint}
        motor_err.append(predicted_motor - measured_motor)
        joint_err.append(predicted_joint - measured_joint)
    return Identified(
        parameters=parameters, relative_std=relative,
        std=dict(zip(PARAMETERS, std, strict=True)), condition_number=condition,
        rmsd_motor=float(np.sqrt(np.mean(np.concatenate(motor_err) ** 2))),
        rmsd_joint=float(np.sqrt(np.mean(np.concatenate(joint_err) ** 2))),
        rows=M.shape[0], fits=fits)
