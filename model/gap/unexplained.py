"""What no library effect explains: structure left in the torque residual after the chosen
effects, found with data-driven maps and never passed off as a named effect.

A map is the residual's mean per bin of one quantity (signed speed, position, gravity load,
time), fitted on some time blocks and scored on the others. Noise cannot be predicted from
held-out blocks, structure can: where a map lowers the held-out error by STRUCTURE_GAIN or
more, the model is wrong along that quantity and the report says where (the bins that carry
the structure). The best such map is offered as a correction, labelled data-driven, with the
held-out gap it closes; the error left after it bounds the noise floor from above.
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


@dataclass(frozen=True)
class Axis:
    name: str
    values: Callable[[Problem], np.ndarray]
    edges: Callable[[np.ndarray], np.ndarray]
    interleaved: bool = False  # folds of CHUNK-second pieces instead of time blocks


def _spread(values: np.ndarray, bins: int) -> np.ndarray:
    return np.linspace(values.min(), values.max() + 1e-9, bins + 1)


def _time_fraction(problem: Problem) -> np.ndarray:
    """Recording index + the fraction of that recording elapsed, so bins never span two."""
    s = problem.s
    out = np.empty(len(s.t))
    for k in np.unique(s.recording):
        rows = s.recording == k
        t = s.t[rows]
        out[rows] = k + 0.999 * (t - t.min()) / max(np.ptp(t), 1e-9)
    return out


AXES = (
    Axis("velocity_rad_s", lambda p: p.s.qd,
         lambda v: np.concatenate([-SPEED_EDGES[::-1], SPEED_EDGES])),
    Axis("position_rad", lambda p: p.s.q, lambda v: _spread(v, 12)),
    Axis("load_nm", lambda p: np.abs(gravity(p.s, p.parameters)[0]), lambda v: _spread(v, 8)),
    Axis("time_fraction", lambda p: _time_fraction(p),
         lambda v: np.concatenate([np.linspace(k, k + 1, 11) for k in np.unique(v.astype(int))]),
         interleaved=True),
)


def _held_out_map(residual: np.ndarray, bins: np.ndarray, folds: np.ndarray) -> np.ndarray:
    """The map's prediction of each row from the rows of the other folds."""
    predicted = np.zeros_like(residual)
    size = int(bins.max()) + 1
    for fold in range(FOLDS):
        test = folds == fold
        sums = np.bincount(bins[~test], weights=residual[~test], minlength=size)
        counts = np.bincount(bins[~test], minlength=size)
        means = np.where(counts >= MIN_BIN_SAMPLES, sums / np.maximum(counts, 1), 0.0)
        predicted[test] = means[bins[test]]
    return predicted


def _where(residual: np.ndarray, values: np.ndarray, edges: np.ndarray) -> list[dict]:
    """The bins carrying the structure: mean residual, RMS and count, largest share first."""
    bins = np.digitize(values, edges)
    rows = []
    for b in np.unique(bins):
        inside = bins == b
        mean = float(residual[inside].mean())
        rows.append({"from": float(edges[b - 1]) if b > 0 else None,
                     "to": float(edges[b]) if b < len(edges) else None,
                     "mean": round(mean, 4), "rmsd": round(rmsd(residual[inside]), 4),
                     "samples": int(inside.sum()), "weight": mean * mean * inside.sum()})
    total = sum(row["weight"] for row in rows)
    named = [row for row in rows if row.pop("weight") >= SHARE * total]
    return sorted(named, key=lambda row: -abs(row["mean"]) * row["samples"])


def unexplained(problem: Problem, residual: np.ndarray) -> tuple[dict, dict | None]:
    """(`unexplained` report section, data-driven correction or None) for the residual the
    chosen effects leave."""
    before = rmsd(residual)
    chunks = np.floor(problem.s.t / CHUNK).astype(int) % FOLDS
    scores = []
    for axis in AXES:
        values = axis.values(problem)
        edges = axis.edges(values)
        bins = np.digitize(values, edges)
        predicted = _held_out_map(residual, bins,
                                  chunks if axis.interleaved else problem.s.segment)
        after = rmsd(residual - predicted)
        scores.append((1.0 - after / before, after, axis, values, edges))
    found = [score for score in scores if score[0] >= STRUCTURE_GAIN]
    report = {
        "found": bool(found),
        "rmsd": round(before, 5),
        "map_held_out_rmsd": {axis.name: round(after, 5) for _, after, axis, _, _ in scores},
        "where": [{"axis": axis.name, "gain": round(gain, 3),
                   "bins": _where(residual, values, edges)}
                  for gain, _, axis, values, edges in sorted(found, key=lambda x: -x[0])],
        "floor_estimate": round(min(after for _, after, *_ in scores), 5),
        "method": f"residual mean per bin of each quantity, fitted on {FOLDS - 1} of {FOLDS} "
                  "folds and scored on the other; structure where it lowers the held-out "
                  f"RMSD by >= {100 * STRUCTURE_GAIN:.0f} % (floor_estimate: the error left "
                  "after the best map, an upper bound on the noise floor)",
    }
    if not found:
        return report, None
    gain, after, axis, values, edges = max(found, key=lambda x: x[0])
    bins = np.digitize(values, edges)
    means = [float(residual[bins == b].mean()) if np.any(bins == b) else 0.0
             for b in range(len(edges) + 1)]
    correction = {
        "kind": f"data-driven correction over {axis.name} (not a physical effect; not in the "
                "model file)",
        "axis": axis.name, "edges": [float(e) for e in edges],
        "torque_nm": [round(m, 5) for m in means],
        "rmsd_without": round(before, 5), "held_out_rmsd_with": round(after, 5),
    }
    return report, correction
