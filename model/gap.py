"""model-gap: where simulation and measurement disagree, which missing effect explains it,
and the model with that effect added.

Evidence comes from two views of the same recordings:
  * torque: the motor torque drive_gain x i against what the model predicts from the measured
    motion (inverse dynamics, the signal the effects act on: they sit in the transmission);
  * motion: the model simulated from the measured state with the measured current, restarted
    every `horizon` seconds, against the measured position.

Candidates (`model.effects`) are fitted together with the motor-side viscous and dry friction
and offset, by least squares; their nonlinear parameter (Stribeck velocity, ripple frequency)
by search. The choice is made on held-out data: K contiguous time blocks, each predicted by a
fit to the others. An effect is named only if it lowers the held-out torque error by at least
MIN_IMPROVEMENT against the plain refit; otherwise the answer is "none" and the model stays.
"""

import math
from dataclasses import dataclass, replace

import numpy as np

from model import dynamics
from model.effects import EFFECT_NAMES
from model.identify import Experiment, IdentificationError, prepare
from model.parameters import GRAVITY, ActuatorModel, ActuatorParameters

HORIZON = 0.5  # s of open-loop simulation before restarting from the measured state
MIN_SPEED = 0.005  # rad/s: below this the joint may be stuck and friction is undetermined
FOLDS = 5
MIN_IMPROVEMENT = 0.10  # held-out torque RMSD must drop by 10 % to name an effect
MISFIT = 0.25  # model torque error above 25 % of the measured torque: wrong model
STRIBECK_VELOCITIES = np.geomspace(0.005, 0.5, 30)  # rad/s
RIPPLE_FREQUENCIES = np.arange(0.5, 40.0, 0.05)  # cycles/rad
SUBSTEPS = 20


class GapError(ValueError):
    """Data or model that model-gap cannot work with; the message says why."""


@dataclass
class Signals:
    """Filtered, decimated signals of all recordings, stacked (the regression rows)."""

    t: np.ndarray
    segment: np.ndarray  # fold index per row (time blocks within each recording)
    recording: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    sign: np.ndarray
    motor_torque: np.ndarray  # drive_gain x current (N.m)
    joint_torque: np.ndarray  # K_j x sensor reading (N.m)
    payload_torque: np.ndarray  # known payload part of the torque
    payload_gravity: np.ndarray  # the payload's gravity torque (part of the transmitted load)


def collect(experiments: list[Experiment], model: ActuatorModel) -> Signals:
    parts = []
    for index, experiment in enumerate(experiments):
        columns = prepare(experiment)
        keep = np.abs(columns.qd) > MIN_SPEED
        p = experiment.payload
        span = columns.t[-1] - columns.t[0]
        parts.append(dict(
            t=columns.t[keep],
            segment=np.minimum((FOLDS * (columns.t - columns.t[0]) / span).astype(int),
                               FOLDS - 1)[keep],
            recording=np.full(keep.sum(), index), q=columns.q[keep], qd=columns.qd[keep],
            qdd=columns.qdd[keep], sign=columns.friction_sign[keep],
            motor_torque=model.parameters.drive_gain * columns.current[keep],
            joint_torque=model.parameters.torque_sensor_gain * columns.joint_torque[keep],
            payload_torque=(p.mass * (p.x**2 + p.y**2) * columns.qdd
                            + GRAVITY * p.mass * (p.y * np.sin(columns.q)
                                                  + p.x * np.cos(columns.q)))[keep],
            payload_gravity=(GRAVITY * p.mass * (p.y * np.sin(columns.q)
                                                 + p.x * np.cos(columns.q)))[keep]))
    return Signals(**{k: np.concatenate([part[k] for part in parts]) for k in parts[0]})


def gravity(s: Signals, parameters: ActuatorParameters) -> np.ndarray:
    return GRAVITY * (parameters.first_moment_y * np.sin(s.q)
                      + parameters.first_moment_x * np.cos(s.q)) + s.payload_gravity


def predicted_motor_torque(s: Signals, parameters: ActuatorParameters) -> np.ndarray:
    """Inverse dynamics of the motor equation, effects included."""
    e = parameters.effects
    g = gravity(s, parameters)
    level = parameters.dry_friction + e.load_friction * np.abs(g)
    if e.stribeck_breakaway:
        level = level + e.stribeck_breakaway * np.exp(-(s.qd / e.stribeck_velocity) ** 2)
    ripple = e.ripple_amplitude * np.sin(2 * np.pi * e.ripple_frequency * s.q + e.ripple_phase)
    return (parameters.inertia * s.qdd + s.payload_torque - s.payload_gravity + g
            + parameters.viscous_friction * s.qd + level * s.sign + parameters.torque_offset
            + ripple)


def predicted_joint_torque(s: Signals, parameters: ActuatorParameters) -> np.ndarray:
    p = parameters
    return (p.link_inertia * s.qdd + s.payload_torque - s.payload_gravity + gravity(s, p)
            + p.viscous_friction_joint * s.qd + p.dry_friction_joint * s.sign
            + p.torque_offset_joint)


# --- candidates -----------------------------------------------------------------------------

def _base_target(s: Signals, parameters: ActuatorParameters) -> np.ndarray:
    """Motor torque minus what the candidates do not touch (inertia, gravity, payload)."""
    return (s.motor_torque - parameters.inertia * s.qdd - s.payload_torque
            + s.payload_gravity - gravity(s, parameters))


def _base_columns(s: Signals) -> np.ndarray:
    return np.column_stack([s.qd, s.sign, np.ones_like(s.qd)])


def _effect_columns(name: str, s: Signals, parameters: ActuatorParameters,
                    shape: float) -> np.ndarray:
    if name == "stribeck":
        return (s.sign * np.exp(-(s.qd / shape) ** 2))[:, None]
    if name == "position_ripple":
        w = 2 * np.pi * shape
        return np.column_stack([np.sin(w * s.q), np.cos(w * s.q)])
    if name == "load_dependent_friction":
        return (s.sign * np.abs(gravity(s, parameters)))[:, None]
    raise KeyError(name)


def _shapes(name: str) -> np.ndarray:
    return {"stribeck": STRIBECK_VELOCITIES, "position_ripple": RIPPLE_FREQUENCIES,
            "load_dependent_friction": np.array([0.0])}[name]


@dataclass
class Fit:
    name: str
    shape: float  # the searched parameter (Stribeck velocity, ripple frequency), else 0
    coefficients: np.ndarray

    def predict(self, s: Signals, parameters: ActuatorParameters) -> np.ndarray:
        return _design(self.name, s, parameters, self.shape) @ self.coefficients


def _design(name: str, s: Signals, parameters: ActuatorParameters, shape: float) -> np.ndarray:
    base = _base_columns(s)
    if name == "none":
        return base
    return np.column_stack([base, _effect_columns(name, s, parameters, shape)])


def fit(name: str, s: Signals, parameters: ActuatorParameters) -> Fit:
    """Least squares of the motor-side friction, offset and the effect; the effect's shape
    parameter by search on the same rows."""
    y = _base_target(s, parameters)
    best = None
    for shape in (_shapes(name) if name != "none" else [0.0]):
        X = _design(name, s, parameters, shape)
        coefficients, *_ = np.linalg.lstsq(X, y, rcond=None)
        error = float(np.sum((X @ coefficients - y) ** 2))
        if best is None or error < best[0]:
            best = (error, Fit(name, float(shape), coefficients))
    return best[1]


def _subset(s: Signals, mask: np.ndarray) -> Signals:
    return Signals(**{k: getattr(s, k)[mask] for k in Signals.__dataclass_fields__})


def held_out_rmsd(name: str, s: Signals, parameters: ActuatorParameters) -> float:
    """Torque RMSD on each time block when fitted on the others (K-fold, contiguous)."""
    squared, count = 0.0, 0
    y = _base_target(s, parameters)
    for fold in range(FOLDS):
        test = s.segment == fold
        if not test.any() or test.all():
            continue
        model_fit = fit(name, _subset(s, ~test), parameters)
        residual = model_fit.predict(_subset(s, test), parameters) - y[test]
        squared += float(residual @ residual)
        count += int(test.sum())
    return math.sqrt(squared / count)


def bic(name: str, s: Signals, parameters: ActuatorParameters) -> float:
    model_fit = fit(name, s, parameters)
    residual = model_fit.predict(s, parameters) - _base_target(s, parameters)
    n = len(residual)
    k = len(model_fit.coefficients) + (name in ("stribeck", "position_ripple"))
    return float(n * math.log(residual @ residual / n) + k * math.log(n))


def improved_parameters(model_fit: Fit, parameters: ActuatorParameters) -> ActuatorParameters:
    """The model with the refitted motor-side friction and offset and the effect set."""
    viscous, dry, offset = model_fit.coefficients[:3]
    out = replace(parameters,
                  viscous_friction_motor=float(viscous - parameters.viscous_friction_joint),
                  dry_friction_motor=float(dry - parameters.dry_friction_joint),
                  torque_offset_motor=float(offset - parameters.torque_offset_joint))
    extra = model_fit.coefficients[3:]
    if model_fit.name == "stribeck":
        return out.with_effect("stribeck", {"breakaway_friction": float(extra[0]),
                                            "velocity": model_fit.shape})
    if model_fit.name == "position_ripple":
        a, b = extra  # a sin(wq) + b cos(wq) = A sin(wq + phase)
        return out.with_effect("position_ripple", {
            "amplitude": float(math.hypot(a, b)), "spatial_frequency": model_fit.shape,
            "phase": float(math.atan2(b, a))})
    if model_fit.name == "load_dependent_friction":
        return out.with_effect("load_dependent_friction", {"coefficient": float(extra[0])})
    return out


# --- motion ---------------------------------------------------------------------------------

def simulation_rmsd(experiments: list[Experiment], parameters: ActuatorParameters,
                    horizon: float = HORIZON) -> tuple[float, list[tuple]]:
    """Position RMSD of simulations driven by the measured current, each started from the
    measured state and run for `horizon`; returns it and the traces (t, measured, simulated)
    of the first recording for plotting."""
    squared, count, traces = 0.0, 0, []
    for index, e in enumerate(experiments):
        t = np.asarray(e.t, float)
        dt = float(np.median(np.diff(t)))
        columns = prepare(Experiment(t, e.q, e.current, e.joint_torque, e.payload, e.name))
        velocity = np.interp(t, columns.t, columns.qd)
        packed = parameters.with_payload(e.payload).packed()
        window = int(round(horizon / dt))
        for start in range(int(0.3 / dt), len(t) - window, window):
            states = dynamics.simulate(float(e.q[start]), float(velocity[start]),
                                       np.asarray(e.current[start + 1:start + 1 + window],
                                                  float), packed, dt, SUBSTEPS)
            error = states[:, 0] - e.q[start + 1:start + 1 + window]
            if not np.all(np.isfinite(error)):
                return math.inf, traces
            squared += float(error @ error)
            count += window
            if index == 0:
                traces.append((t[start + 1:start + 1 + window],
                               np.asarray(e.q[start + 1:start + 1 + window]), states[:, 0]))
    return math.sqrt(squared / count), traces


# --- where ----------------------------------------------------------------------------------

def localise(s: Signals, residual: np.ndarray, parameters: ActuatorParameters) -> dict:
    """Residual RMS binned by speed, position, load and time: where the model is wrong."""
    def binned(values: np.ndarray, edges: np.ndarray) -> list[dict]:
        out = []
        for low, high in zip(edges[:-1], edges[1:], strict=True):
            inside = (values >= low) & (values < high)
            if inside.sum() >= 10:
                out.append({"from": round(float(low), 4), "to": round(float(high), 4),
                            "rmsd": round(float(np.sqrt(np.mean(residual[inside] ** 2))), 4),
                            "samples": int(inside.sum())})
        return out

    speed = np.abs(s.qd)
    load = np.abs(gravity(s, parameters))
    return {
        "by_speed_rad_s": binned(speed, np.array([0, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 50])),
        "by_position_rad": binned(s.q, np.linspace(s.q.min(), s.q.max() + 1e-9, 11)),
        "by_load_nm": binned(load, np.linspace(0, load.max() + 1e-9, 9)),
        "by_time_s": binned(s.t, np.linspace(s.t.min(), s.t.max() + 1e-9, 11)),
    }


# --- the workflow ---------------------------------------------------------------------------

@dataclass
class GapResult:
    effect: str
    rmsd_before: float
    rmsd_after: float
    sim_rmsd_before: float
    sim_rmsd_after: float
    rmsd_sensor_before: float
    rmsd_sensor_after: float
    horizon: float
    candidates: dict
    parameters: ActuatorParameters  # improved (or unchanged when effect == "none")
    localisation_before: dict
    localisation_after: dict
    residuals: dict  # for plots: speed, position, before, after
    traces_before: list
    traces_after: list


def find_gap(experiments: list[Experiment], model: ActuatorModel,
             horizon: float = HORIZON) -> GapResult:
    try:
        s = collect(experiments, model)
    except IdentificationError as exc:
        raise GapError(str(exc)) from None
    parameters = model.parameters
    residual_before = s.motor_torque - predicted_motor_torque(s, parameters)
    rmsd_before = float(np.sqrt(np.mean(residual_before**2)))
    scale = float(np.sqrt(np.mean(s.motor_torque**2)))
    if rmsd_before > MISFIT * scale:
        raise GapError(
            f"the model {model.source or model.name} does not fit these recordings: its torque "
            f"error is {rmsd_before:.2f} N.m, {100 * rmsd_before / scale:.0f} % of the measured "
            f"{scale:.2f} N.m (model-gap expects below {100 * MISFIT:.0f} %); identify a model "
            "for this actuator first")
    baseline = held_out_rmsd("none", s, parameters)
    candidates = {"none": {"held_out_rmsd": round(baseline, 5), "bic": round(
        bic("none", s, parameters), 1)}}
    for name in EFFECT_NAMES:
        score = held_out_rmsd(name, s, parameters)
        model_fit = fit(name, s, parameters)
        candidates[name] = {"held_out_rmsd": round(score, 5),
                            "improvement": round(1 - score / baseline, 4),
                            "bic": round(bic(name, s, parameters), 1),
                            "shape": model_fit.shape}
    best = min(EFFECT_NAMES, key=lambda n: candidates[n]["held_out_rmsd"])
    effect = best if candidates[best]["improvement"] >= MIN_IMPROVEMENT else "none"
    improved = (improved_parameters(fit(effect, s, parameters), parameters)
                if effect != "none" else parameters)
    residual_after = s.motor_torque - predicted_motor_torque(s, improved)
    sim_before, traces_before = simulation_rmsd(experiments, parameters, horizon)
    sim_after, traces_after = simulation_rmsd(experiments, improved, horizon)
    sensor_before = s.joint_torque - predicted_joint_torque(s, parameters)
    sensor_after = s.joint_torque - predicted_joint_torque(s, improved)
    return GapResult(
        effect=effect, rmsd_before=rmsd_before,
        rmsd_after=float(np.sqrt(np.mean(residual_after**2))),
        sim_rmsd_before=sim_before, sim_rmsd_after=sim_after,
        rmsd_sensor_before=float(np.sqrt(np.mean(sensor_before**2))),
        rmsd_sensor_after=float(np.sqrt(np.mean(sensor_after**2))),
        horizon=horizon, candidates=candidates, parameters=improved,
        localisation_before=localise(s, residual_before, parameters),
        localisation_after=localise(s, residual_after, improved),
        residuals={"speed": s.qd, "position": s.q, "before": residual_before,
                   "after": residual_after},
        traces_before=traces_before, traces_after=traces_after)
