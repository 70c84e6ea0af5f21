"""Candidate explanations of a gap: the motor-side friction and offset refitted by least
squares, with effects from the registry (`model.effects`) added as regressor columns; each
effect's nonlinear shape parameter (Stribeck velocity, ripple frequency) found by scanning its
grid and refining around the best point."""

from dataclasses import dataclass, replace

import numpy as np

from model.effects import Effect, Effects
from model.gap.evidence import Signals, gravity, predicted_motor_torque, unit_columns
from model.parameters import ActuatorParameters

REFIT = ("viscous_friction_motor", "dry_friction_motor", "torque_offset_motor")
REFINE_POINTS = 21  # between the best grid point's neighbours


@dataclass(frozen=True)
class Term:
    """An effect at a given shape (0 for effects without one)."""

    effect: Effect
    shape: float


class Problem:
    """The fixed part of every candidate fit on a set of rows: the motor torque minus what the
    refit does not touch (inertia, gravity, payload, the joint-side friction and offset), the
    base columns of REFIT, and what the effects' columns need."""

    def __init__(self, s: Signals, parameters: ActuatorParameters):
        self.s = s
        self.parameters = parameters
        untouched = replace(parameters, effects=Effects(), **dict.fromkeys(REFIT, 0.0))
        self.target = s.motor_torque - predicted_motor_torque(s, untouched)
        self.base = unit_columns(s, parameters, REFIT)
        self.gravity, self.slope = gravity(s, parameters)

    def columns(self, term: Term) -> np.ndarray:
        s = self.s
        return term.effect.columns(s.q, s.qd, s.sign, self.parameters.dry_friction,
                                   self.gravity, self.slope, term.shape)

    def design(self, terms: tuple[Term, ...]) -> np.ndarray:
        return np.column_stack([self.base, *(self.columns(term) for term in terms)])


@dataclass
class Fit:
    terms: tuple[Term, ...]
    coefficients: np.ndarray  # REFIT's values, then each term's coefficients in order

    def effect_coefficients(self) -> list[np.ndarray]:
        out, start = [], len(REFIT)
        for term in self.terms:
            out.append(self.coefficients[start:start + term.effect.coefficients])
            start += term.effect.coefficients
        return out

    def predict(self, problem: Problem, rows: np.ndarray | slice = slice(None)) -> np.ndarray:
        return problem.design(self.terms)[rows] @ self.coefficients

    def tables(self) -> dict[str, dict[str, float]]:
        """Each term's TOML table from its fitted coefficients."""
        return {term.effect.name: term.effect.table_from_fit(term.shape, coefficients)
                for term, coefficients in zip(self.terms, self.effect_coefficients(),
                                              strict=True)}


def solve(problem: Problem, terms: tuple[Term, ...], rows: np.ndarray | slice = slice(None)
          ) -> Fit:
    coefficients, *_ = np.linalg.lstsq(problem.design(terms)[rows], problem.target[rows],
                                       rcond=None)
    return Fit(terms, coefficients)


class _Projection:
    """Least squares of y on [fixed | C] for many candidate blocks C: the fixed columns are
    projected out once (QR), so each candidate costs a small solve."""

    def __init__(self, fixed: np.ndarray, y: np.ndarray):
        self.basis, _ = np.linalg.qr(fixed)
        self.y = y - self.basis @ (self.basis.T @ y)

    def sse(self, candidate: np.ndarray) -> float:
        c = candidate - self.basis @ (self.basis.T @ candidate)
        g = c.T @ self.y
        beta, *_ = np.linalg.lstsq(c.T @ c, g, rcond=None)
        return float(self.y @ self.y - g @ beta)


def best_terms(problem: Problem, fixed: tuple[Term, ...], effect: Effect,
               row_sets: list[np.ndarray | slice]) -> list[Term]:
    """For each set of rows, the shape of `effect` that, added to `fixed`, leaves the least
    squared error on those rows."""
    if effect.shape is None:
        return [Term(effect, 0.0) for _ in row_sets]
    design = problem.design(fixed)
    projections = [_Projection(design[rows], problem.target[rows]) for rows in row_sets]

    def errors(shape: float, which: list[int]) -> list[float]:
        block = problem.columns(Term(effect, shape))
        return [projections[j].sse(block[row_sets[j]]) for j in which]

    grid = effect.shape_grid
    everyone = list(range(len(row_sets)))
    table = np.array([errors(shape, everyone) for shape in grid])
    out = []
    for j in everyone:
        i = int(np.argmin(table[:, j]))
        fine = np.linspace(grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)], REFINE_POINTS)
        scores = [errors(shape, [j])[0] for shape in fine]
        out.append(Term(effect, float(fine[int(np.argmin(scores))])))
    return out


def improved_parameters(fit: Fit, parameters: ActuatorParameters) -> ActuatorParameters:
    """The model with the refitted motor-side friction and offset and exactly the fitted
    effects."""
    return replace(parameters, effects=Effects(fit.tables()),
                   **{name: float(value) for name, value in zip(REFIT, fit.coefficients,
                                                                strict=False)})
