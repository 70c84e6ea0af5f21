"""What no library effect explains: structure left in a residual, found with data-driven maps
and never passed off as a named effect.

A map is the residual's mean per bin of one quantity (signed speed, signed current: the
drive's own axis, position, gravity load, time since the start of the recording), fitted on
some time blocks and scored on the others.
Friction changes sign with the motion, so its residual averages out in a bin of position,
load or time that both directions cross: each of those quantities is therefore also mapped as
a friction level (the residual along the direction of motion, `friction_over_*`). Noise cannot
be predicted from held-out blocks, structure can: where a map lowers the held-out error by
STRUCTURE_GAIN or more, the model is wrong along that quantity and the report says where (the
bins that carry the structure). The best such map is offered as a correction, labelled
data-driven, with the held-out gap it closes; the error left after it bounds the noise floor
from above.

Time gets one more look (`drift`): a drift lives in the first seconds of each recording, so
the whole recording's RMSD is a blunt judge of it. Instead the residual's level is taken per
CHUNK of each recording (as a torque, and along the direction of motion: a friction level,
which a bin of time would average out), and those levels are fitted against the time since
the start of their recording by a exp(-t / tau) + b, tau on a grid, beside the chunk's mean
speed (exciting trajectories change speed as they go, so a speed-dependent misfit would pass
for a drift); the scatter of the levels about the fit gives the standard error of a. The
first STARTING seconds (the joint leaving rest, tracking settling) are left out, and time
constants start at FASTEST_DRIFT. Where a is DRIFT_Z standard errors from zero and the decay
it makes over the longest recording is at least DRIFT_SIZE residual RMSDs, the model drifts
over a recording (a gear warming up, an offset settling) and the report gives the time
constant with the range the data cannot tell from it, and the decay within the recordings
(the level at the start only when the range is bounded).

The same maps serve each instrument on its own (`structure`): the motor side (drive gain x
current) and the joint torque sensor.
"""

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from model.gap.candidates import Problem
from model.gap.evidence import FOLDS, gravity, rmsd

STRUCTURE_GAIN = 0.20  # a map must lower the held-out torque RMSD by 20 % to count
MIN_BIN_SAMPLES = 5  # training samples a bin needs before its mean is used
CHUNK = 0.5  # s: time maps are scored on interleaved chunks (a held-out block has no time bins)
SHARE = 0.10  # a bin is named where it carries 10 % of the structure or more
SPEED_EDGES = np.array([0.005, 0.01, 0.02, 0.04, 0.08, 0.16, 0.32, 0.64, 1.28, 2.56, 50.0])
TIME_CONSTANTS = 40  # points of the drift's time-constant grid
SLOWEST = 10.0  # the grid's longest time constant, in recording lengths
DRIFT_Z = 5.0  # standard errors a drift's amplitude needs
DRIFT_SIZE = 1.0  # ... and its decay over the longest recording, in residual RMSDs
STARTING = 1.0  # s: the start of each recording, motion leaving rest, is no drift evidence
FASTEST_DRIFT = 2.0  # s: the shortest time constant taken for a drift, not a start-up


@dataclass(frozen=True)
class Axis:
    name: str
    values: Callable[[Problem], np.ndarray]
    edges: Callable[[np.ndarray], np.ndarray]
    interleaved: bool = False  # folds of CHUNK-second pieces instead of time blocks
    friction: bool = False  # a map of the level along the direction of motion


def _spread(values: np.ndarray, bins: int) -> np.ndarray:
    return np.linspace(values.min(), values.max() + 1e-9, bins + 1)


def _speed_edges(values: np.ndarray) -> np.ndarray:
    return np.concatenate([-SPEED_EDGES[::-1], SPEED_EDGES])


def _position(p: Problem) -> np.ndarray:
    return p.s.q


def _load(p: Problem) -> np.ndarray:
    return np.abs(gravity(p.s, p.parameters)[0])


def _elapsed(p: Problem) -> np.ndarray:
    return p.s.elapsed


def _axes() -> tuple[Axis, ...]:
    torque_and_friction = []
    for name, values, bins, interleaved in (("position_rad", _position, 12, False),
                                            ("load_nm", _load, 8, False),
                                            ("time_since_start_s", _elapsed, 10, True)):
        for friction in (False, True):
            torque_and_friction.append(Axis(
                f"friction_over_{name}" if friction else name, values,
                lambda v, bins=bins: _spread(v, bins), interleaved, friction))
    return (Axis("velocity_rad_s", lambda p: p.s.qd, _speed_edges),
            Axis("current_a", lambda p: p.s.current, lambda v: _spread(v, 12)),
            *torque_and_friction)


AXES = _axes()


def _weight(problem: Problem, axis: Axis) -> np.ndarray:
    """What the map's value multiplies: the direction of motion for a friction level."""
    return problem.s.sign if axis.friction else np.ones(len(problem.s.t))


def _folds(problem: Problem, interleaved: bool) -> np.ndarray:
    return (np.floor(problem.s.t / CHUNK).astype(int) % FOLDS if interleaved
            else problem.s.segment)


def _held_out_map(residual: np.ndarray, weight: np.ndarray, bins: np.ndarray,
                  folds: np.ndarray) -> np.ndarray:
    """The map's prediction of each row from the rows of the other folds (per bin, the least-
    squares value m of residual = m x weight)."""
    predicted = np.zeros_like(residual)
    size = int(bins.max()) + 1
    for fold in range(FOLDS):
        test = folds == fold
        sums = np.bincount(bins[~test], weights=residual[~test] * weight[~test],
                           minlength=size)
        norms = np.bincount(bins[~test], weights=weight[~test] ** 2, minlength=size)
        counts = np.bincount(bins[~test], minlength=size)
        means = np.where(counts >= MIN_BIN_SAMPLES, sums / np.maximum(norms, 1e-12), 0.0)
        predicted[test] = means[bins[test]] * weight[test]
    return predicted


def _bin_means(residual: np.ndarray, weight: np.ndarray, bins: np.ndarray, size: int
               ) -> np.ndarray:
    sums = np.bincount(bins, weights=residual * weight, minlength=size)
    norms = np.bincount(bins, weights=weight**2, minlength=size)
    return np.where(norms > 0, sums / np.maximum(norms, 1e-12), 0.0)


def _where(residual: np.ndarray, weight: np.ndarray, values: np.ndarray, edges: np.ndarray
           ) -> list[dict]:
    """The bins carrying the structure: mean (a torque, or a friction level), RMS and count,
    largest share first."""
    bins = np.digitize(values, edges)
    means = _bin_means(residual, weight, bins, len(edges) + 1)
    rows = []
    for b in np.unique(bins):
        inside = bins == b
        rows.append({"from": float(edges[b - 1]) if b > 0 else None,
                     "to": float(edges[b]) if b < len(edges) else None,
                     "mean": round(float(means[b]), 4), "rmsd": round(rmsd(residual[inside]), 4),
                     "samples": int(inside.sum()),
                     "weight": float(means[b] ** 2 * np.sum(weight[inside] ** 2))})
    total = sum(row["weight"] for row in rows)
    named = [row for row in rows if row.pop("weight") >= SHARE * total]
    return sorted(named, key=lambda row: -abs(row["mean"]) * row["samples"])


@dataclass(frozen=True)
class Score:
    gain: float  # 1 - held-out RMSD with the map / without
    after: float  # held-out RMSD with the map
    axis: Axis
    values: np.ndarray
    edges: np.ndarray


def scores(problem: Problem, residual: np.ndarray) -> list[Score]:
    """Every axis's map of `residual`, scored on held-out folds."""
    before = rmsd(residual)
    out = []
    for axis in AXES:
        values = axis.values(problem)
        edges = axis.edges(values)
        predicted = _held_out_map(residual, _weight(problem, axis), np.digitize(values, edges),
                                  _folds(problem, axis.interleaved))
        after = rmsd(residual - predicted)
        out.append(Score(1.0 - after / before, after, axis, values, edges))
    return out


def drift(problem: Problem, residual: np.ndarray) -> dict:
    """The best exponential in the time since the start of each recording, as a torque or as
    a friction level, fitted to the residual's level per CHUNK (see the module docstring)."""
    s = problem.s
    _, chunk = np.unique(s.recording * 1_000_000 + np.floor(s.t / CHUNK).astype(int),
                         return_inverse=True)
    t = np.bincount(chunk, s.elapsed) / np.bincount(chunk)
    speed = np.bincount(chunk, np.abs(s.qd)) / np.bincount(chunk)
    span = max(float(s.elapsed.max()), 1e-3)
    grid = np.geomspace(FASTEST_DRIFT, max(SLOWEST * span, 2 * FASTEST_DRIFT), TIME_CONSTANTS)
    best: dict = {}
    for kind, weight in (("torque", np.ones(len(s.t))), ("friction level", s.sign)):
        norm = np.bincount(chunk, weight**2)
        used = (norm > 0) & (t >= STARTING)
        level = np.bincount(chunk, residual * weight)[used] / norm[used]
        fits = []
        for tau in grid:
            x = np.column_stack([np.exp(-t[used] / tau), np.ones(used.sum()), speed[used]])
            beta, *_ = np.linalg.lstsq(x, level, rcond=None)
            fits.append((float(np.sum((x @ beta - level) ** 2)), beta, x))
        errors = np.array([error for error, _, _ in fits])
        k = int(np.argmin(errors))
        _, (amplitude, *_), x = fits[k]
        dof = max(len(level) - 4, 1)  # amplitude, constant, speed, time constant
        variance = errors[k] / dof
        covariance = variance * np.linalg.inv(x.T @ x)
        z = float(amplitude / np.sqrt(covariance[0, 0]))
        if best and abs(z) <= abs(best["z"]):
            continue
        # the time constants the data cannot tell from the best (about 95 %); one the data do
        # not bound leaves the level at the start unknown (only the decay within is measured)
        alike = grid[errors <= errors[k] + 4.0 * variance]
        unbounded = bool(alike.max() >= grid[-1])
        best = {"kind": kind, "z": round(z, 2),
                "time_constant_s": round(float(grid[k]), 2),
                "time_constant_range_s": [round(float(alike.min()), 2),
                                          round(float(alike.max()), 2)],
                "decay_over_longest_recording_nm": round(
                    float(amplitude * (1.0 - np.exp(-span / grid[k]))), 4),
                "excess_at_start_nm": None if unbounded else round(float(amplitude), 4),
                "slower_than_the_recordings": unbounded,
                "longest_recording_s": round(span, 2), "chunks": int(len(level))}
    best["found"] = bool(abs(best["z"]) >= DRIFT_Z and abs(
        best["decay_over_longest_recording_nm"]) >= DRIFT_SIZE * rmsd(residual))
    best["method"] = (f"the residual's level in each {CHUNK} s chunk (as a torque, or along the "
                      "direction of motion: a friction level) from "
                      f"{STARTING:g} s after the start of its recording, fitted by "
                      "a exp(-t / tau) + b + c |qd| (the chunk's mean speed) with tau on a grid "
                      f"from {FASTEST_DRIFT:g} s to {SLOWEST:g} recording lengths; found where a "
                      f"is {DRIFT_Z:g} or more standard errors from zero (the chunks' scatter "
                      f"about the fit) and the decay it makes over the longest recording is "
                      f"{DRIFT_SIZE:g} residual RMSD or more")
    return best


def structure(problem: Problem, residual: np.ndarray,
              everything: list[Score] | None = None) -> dict:
    """Where `residual` has structure: the held-out error of each axis's map (`everything`,
    when already scored), the axes that pass STRUCTURE_GAIN with the bins that carry it, and
    the drift over time."""
    everything = everything if everything is not None else scores(problem, residual)
    found = sorted((s for s in everything if s.gain >= STRUCTURE_GAIN), key=lambda s: -s.gain)
    over_time = drift(problem, residual)
    return {
        "found": bool(found) or over_time["found"],
        "rmsd": round(rmsd(residual), 5),
        "map_held_out_rmsd": {s.axis.name: round(s.after, 5) for s in everything},
        "where": [{"axis": s.axis.name, "gain": round(s.gain, 3),
                   "bins": _where(residual, _weight(problem, s.axis), s.values, s.edges)}
                  for s in found],
        "drift": over_time,
        "floor_estimate": round(min(s.after for s in everything), 5),
        "method": f"residual mean per bin of each quantity (friction_over_*: along the "
                  f"direction of motion), fitted on {FOLDS - 1} of {FOLDS} folds and scored on "
                  f"the other; structure where it lowers the held-out RMSD by >= "
                  f"{100 * STRUCTURE_GAIN:.0f} % (floor_estimate: the error left after the best"
                  " map, an upper bound on the noise floor)",
    }


def unexplained(problem: Problem, residual: np.ndarray) -> tuple[dict, dict | None]:
    """(`unexplained` report section, data-driven correction or None) for the residual the
    chosen effects leave."""
    everything = scores(problem, residual)
    report = structure(problem, residual, everything)
    found = [s for s in everything if s.gain >= STRUCTURE_GAIN]
    if not found:
        return report, None
    best = max(found, key=lambda s: s.gain)
    weight = _weight(problem, best.axis)
    means = _bin_means(residual, weight, np.digitize(best.values, best.edges),
                       len(best.edges) + 1)
    correction = {
        "kind": f"data-driven correction over {best.axis.name} (not a physical effect; not in "
                "the model file)",
        "axis": best.axis.name, "edges": [float(e) for e in best.edges],
        "torque_nm": [round(float(m), 5) for m in means],
        "along_direction_of_motion": best.axis.friction,
        "rmsd_without": round(rmsd(residual), 5), "held_out_rmsd_with": round(best.after, 5),
    }
    return report, correction
