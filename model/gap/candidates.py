"""Candidate explanations of a gap: the motor-side friction and offset refitted by least
squares, with effects from the registry (`model.effects`) added as regressor columns; each
effect's nonlinear shape parameter (Stribeck velocity, ripple frequency) found by scanning its
grid and refining around the best point.

The drive gain is refitted too: a baseline identified without an effect has compromised on
its gain (a saturating torque constant most of all: between low and high currents), and an
effect cannot be fitted around a wrong gain. It is refitted in every candidate, "none"
included, so no effect wins by the gain alone. Its column is the measured motor torque
(drive_gain x current): its coefficient a is the gain's relative change (new gain =
(1 - a) x old), and drive-side effects' coefficients, fitted against the old gain, are
divided by (1 - a)."""

from dataclasses import dataclass, replace

import numpy as np

from model.effects import Effect, Effects
from model.gap.evidence import FOLDS, Signals, predicted_motor_torque, regressors, unit_columns
from model.parameters import ActuatorParameters

REFIT = ("viscous_friction_motor", "dry_friction_motor", "torque_offset_motor")  # + the gain
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
        # rows ordered by time block, so that a block is a slice
        s = s.subset(np.argsort(s.segment, kind="stable"))
        bounds = np.searchsorted(s.segment, np.arange(FOLDS + 1))
        self.blocks = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
        self.s = s
        self.parameters = parameters
        untouched = replace(parameters, effects=Effects(), **dict.fromkeys(REFIT, 0.0))
        self.target = s.motor_torque - predicted_motor_torque(s, untouched)
        self.base = unit_columns(s, parameters, REFIT)
        self.rows = regressors(s, parameters)

    def columns(self, term: Term) -> np.ndarray:
        return term.effect.columns(self.rows, term.shape)

    def design(self, terms: tuple[Term, ...]) -> np.ndarray:
        return np.column_stack([self.base, self.s.motor_torque,
                                *(self.columns(term) for term in terms)])


@dataclass
class Fit:
    terms: tuple[Term, ...]
    coefficients: np.ndarray  # REFIT's values, then each term's coefficients in order

    @property
    def gain_ratio(self) -> float:
        """The refitted drive gain over the old one."""
        return 1.0 - self.coefficients[len(REFIT)]

    def effect_coefficients(self) -> list[np.ndarray]:
        out, start = [], len(REFIT) + 1
        for term in self.terms:
            coefficients = self.coefficients[start:start + term.effect.coefficients]
            if term.effect.side == "drive":
                coefficients = coefficients / self.gain_ratio
            out.append(coefficients)
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


def best_terms(problem: Problem, fixed: tuple[Term, ...], effect: Effect,
               left_out: list[int | None]) -> list[Term]:
    """For each entry of `left_out` (a time block left out, or None for none), the shape of
    `effect` that, added to `fixed`, leaves the least squared error on the remaining rows.

    The rows' cross products are summed per time block, so a fit on any union of blocks is a
    small solve: one pass over the data per shape serves every fold. The grid's best point is
    refined between its neighbours."""
    if effect.shape is None:
        return [Term(effect, 0.0) for _ in left_out]
    pick = np.array([[fold != block for block in range(FOLDS)] for fold in left_out], float)
    # the columns of `fixed` once, not once a shape (the same values: a ripple's harmonics
    # were a tenth of a model-gap case's time, recomputed for each of ~40 shapes)
    fixed_design = problem.design(fixed)

    def errors(shape: float) -> np.ndarray:
        """Squared error of each entry of `left_out` at this shape."""
        z = np.column_stack([fixed_design, problem.columns(Term(effect, shape)),
                             problem.target])
        grams = np.array([z[rows].T @ z[rows] for rows in problem.blocks])
        gram = np.einsum("fb,bij->fij", pick, grams)
        a, b = gram[:, :-1, :-1], gram[:, :-1, -1]
        ridge = 1e-12 * np.trace(a, axis1=1, axis2=2)[:, None, None] * np.eye(a.shape[1])
        beta = np.linalg.solve(a + ridge, b[..., None])[..., 0]
        return gram[:, -1, -1] - np.einsum("fi,fi->f", b, beta)

    grid = effect.grid(problem.rows)
    coarse = np.array([errors(shape) for shape in grid])
    best = np.argmin(coarse, axis=0)
    fine_grids = [np.linspace(grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)],
                              REFINE_POINTS) for i in best]
    shapes = np.unique(np.concatenate(fine_grids))
    fine = dict(zip(shapes, (errors(shape) for shape in shapes), strict=True))
    return [Term(effect, float(min(points, key=lambda x, j=j: fine[x][j])))
            for j, points in enumerate(fine_grids)]


def improved_parameters(fit: Fit, parameters: ActuatorParameters) -> ActuatorParameters:
    """The model with the refitted motor-side friction, offset and drive gain and exactly the
    fitted effects."""
    return replace(parameters, effects=Effects(fit.tables()),
                   drive_gain=parameters.drive_gain * fit.gain_ratio,
                   **{name: float(value) for name, value in zip(REFIT, fit.coefficients,
                                                                strict=False)})
