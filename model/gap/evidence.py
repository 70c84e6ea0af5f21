"""Evidence of a gap: the recordings as regression rows, what the model predicts for them, and
where model and measurement disagree.

Two views of the same recordings:
  * torque: the torque the measured current makes (drive_gain x i, less what drive-side
    effects lose) against the inverse dynamics of the measured motion (the signal the effects
    act on), and, on its own, the joint torque sensor against the inverse dynamics' joint
    side: two instruments, so a residual in one and not the other says which side is wrong;
  * motion: the model simulated from the measured state with the measured current, restarted
    every `horizon` seconds, against the measured position.
"""

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from model import dynamics
from model.effects import Effects, Regressors
from model.identify import Experiment, prepare
from model.parameters import ActuatorModel, ActuatorParameters, Payload

MIN_SPEED = 0.005  # rad/s: below this the joint may be stuck and friction is undetermined
FOLDS = 5  # contiguous time blocks per recording for held-out scores
SETTLE = 0.3  # s at the start of a recording left out of the simulations (tracking settles)


@dataclass
class Signals:
    """Filtered, decimated signals of all recordings, stacked (the regression rows)."""

    t: np.ndarray
    segment: np.ndarray  # fold index per row (time blocks within each recording)
    recording: np.ndarray  # index into `payloads` per row
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    sign: np.ndarray  # filtered sign(qd): the dry friction's direction
    current: np.ndarray  # A, filtered
    elapsed: np.ndarray  # s since the start of the row's recording
    motor_torque: np.ndarray  # drive_gain x current (N.m)
    joint_torque: np.ndarray  # K_j x sensor reading (N.m)
    payloads: tuple[Payload, ...]

    def subset(self, mask: np.ndarray) -> "Signals":
        return Signals(**{f.name: getattr(self, f.name)[mask] for f in fields(self)
                          if f.name != "payloads"}, payloads=self.payloads)


def collect(experiments: list[Experiment], model: ActuatorModel) -> Signals:
    """The rows of every recording moving faster than MIN_SPEED; IdentificationError when a
    recording cannot be used."""
    parts = []
    for index, experiment in enumerate(experiments):
        columns = prepare(experiment)
        keep = np.abs(columns.qd) > MIN_SPEED
        span = columns.t[-1] - columns.t[0]
        parts.append(dict(
            t=columns.t[keep],
            segment=np.minimum((FOLDS * (columns.t - columns.t[0]) / span).astype(int),
                               FOLDS - 1)[keep],
            recording=np.full(keep.sum(), index), q=columns.q[keep], qd=columns.qd[keep],
            qdd=columns.qdd[keep], sign=columns.friction_sign[keep],
            current=columns.current[keep], elapsed=columns.t[keep] - float(experiment.t[0]),
            motor_torque=model.parameters.drive_gain * columns.current[keep],
            joint_torque=model.parameters.torque_sensor_gain * columns.joint_torque[keep]))
    return Signals(**{k: np.concatenate([part[k] for part in parts]) for k in parts[0]},
                   payloads=tuple(e.payload for e in experiments))


def _per_recording(s: Signals, parameters: ActuatorParameters, function) -> tuple:
    """`function(rows, packed)` evaluated on each recording's rows with that recording's
    payload in the parameters, the results put back in row order."""
    out = None
    for index, payload in enumerate(s.payloads):
        rows = s.recording == index
        parts = function(rows, parameters.with_payload(payload).packed())
        if out is None:
            out = tuple(np.empty(len(s.t)) for _ in parts)
        for whole, part in zip(out, parts, strict=True):
            whole[rows] = part
    return out


def predicted_torques(s: Signals, parameters: ActuatorParameters) -> tuple:
    """(motor, joint) torques of the model's inverse dynamics for the measured motion, each
    row at its time since the start when an effect drifts over time."""
    def inverse(rows: np.ndarray, p: np.ndarray) -> tuple:
        if not dynamics.drifts(p):
            return dynamics.inverse_dynamics(s.q[rows], s.qd[rows], s.qdd[rows], s.sign[rows],
                                             p)
        out = np.array([dynamics.sample_inverse_dynamics(
            q, qd, qdd, sign, dynamics.at_elapsed(p, elapsed)) for q, qd, qdd, sign, elapsed
            in zip(s.q[rows], s.qd[rows], s.qdd[rows], s.sign[rows], s.elapsed[rows],
                   strict=True)])
        return out[:, 0], out[:, 1]

    return _per_recording(s, parameters, inverse)


def residuals(s: Signals, parameters: ActuatorParameters) -> tuple[np.ndarray, np.ndarray]:
    """Each instrument's residual on its own: (the torque the measured current makes minus the
    motor torque the model needs, the torque sensor minus the model's joint torque)."""
    motor, joint = predicted_torques(s, parameters)
    made = dynamics.motor_torque(s.current, parameters.packed())
    return made - motor, s.joint_torque - joint


def regressors(s: Signals, parameters: ActuatorParameters) -> Regressors:
    """What effects' regressor columns are computed from on these rows."""
    g, slope = gravity(s, parameters)
    return Regressors(q=s.q, qd=s.qd, direction=s.sign, current=s.current, elapsed=s.elapsed,
                      gravity=g, d_gravity=slope, coulomb=parameters.dry_friction,
                      drive_gain=parameters.drive_gain)


def predicted_motor_torque(s: Signals, parameters: ActuatorParameters) -> np.ndarray:
    return predicted_torques(s, parameters)[0]


def gravity(s: Signals, parameters: ActuatorParameters) -> tuple:
    """The model's gravity torque per row (payload included) and its slope dG/dq."""
    return _per_recording(s, parameters,
                          lambda rows, p: dynamics.gravity_and_slope(s.q[rows], p))


def unit_columns(s: Signals, parameters: ActuatorParameters, names: tuple[str, ...],
                 side: int = 0) -> np.ndarray:
    """Regressor columns of base parameters for the motor torque (side 0) or the joint torque
    (side 1): the inverse dynamics is linear in them, so each column is the torque of a unit
    value with every other parameter (and the payload) zero."""
    nothing = replace(parameters, effects=Effects(),
                      **{f.name: 0.0 for f in fields(parameters) if f.name != "effects"})
    return np.column_stack([
        dynamics.inverse_dynamics(s.q, s.qd, s.qdd, s.sign,
                                  replace(nothing, **{name: 1.0}).packed())[side]
        for name in names])


def rmsd(residual: np.ndarray) -> float:
    return float(np.sqrt(np.mean(residual**2)))


def simulation_rmsd(experiments: list[Experiment], parameters: ActuatorParameters,
                    horizon: float) -> tuple[float, list[tuple]]:
    """Position RMSD of simulations driven by the measured current, each started from the
    measured state and run for `horizon`; returns it and the traces (t, measured, simulated)
    of the first recording for plotting."""
    squared, count, traces = 0.0, 0, []
    for index, e in enumerate(experiments):
        t = np.asarray(e.t, float)
        dt = float(np.median(np.diff(t)))
        columns = prepare(e)
        velocity = np.interp(t, columns.t, columns.qd)
        packed = parameters.with_payload(e.payload).packed()
        window = int(round(horizon / dt))
        for start in range(int(SETTLE / dt), len(t) - window, window):
            states = dynamics.simulate(float(e.q[start]), float(velocity[start]),
                                       np.asarray(e.current[start + 1:start + 1 + window],
                                                  float),
                                       dynamics.at_elapsed(packed, t[start] - t[0]), dt,
                                       dynamics.SUBSTEPS)
            error = states[:, 0] - e.q[start + 1:start + 1 + window]
            if not np.all(np.isfinite(error)):
                return math.inf, traces
            squared += float(error @ error)
            count += window
            if index == 0:
                traces.append((t[start + 1:start + 1 + window],
                               np.asarray(e.q[start + 1:start + 1 + window]), states[:, 0]))
    return math.sqrt(squared / count), traces


def localise(s: Signals, residual: np.ndarray, parameters: ActuatorParameters) -> dict:
    """Residual RMS binned by speed, position, load and time: where the model is wrong."""
    def binned(values: np.ndarray, edges: np.ndarray) -> list[dict]:
        out = []
        for low, high in zip(edges[:-1], edges[1:], strict=True):
            inside = (values >= low) & (values < high)
            if inside.sum() >= 10:
                out.append({"from": round(float(low), 4), "to": round(float(high), 4),
                            "rmsd": round(rmsd(residual[inside]), 4),
                            "samples": int(inside.sum())})
        return out

    speed = np.abs(s.qd)
    load = np.abs(gravity(s, parameters)[0])
    return {
        "by_speed_rad_s": binned(speed, np.array([0, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 50])),
        "by_position_rad": binned(s.q, np.linspace(s.q.min(), s.q.max() + 1e-9, 11)),
        "by_load_nm": binned(load, np.linspace(0, load.max() + 1e-9, 9)),
        "by_time_s": binned(s.t, np.linspace(s.t.min(), s.t.max() + 1e-9, 11)),
    }
