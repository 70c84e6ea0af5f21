"""The choice between candidates, made on held-out data: each recording is cut into FOLDS
contiguous time blocks and each block is predicted by a fit (shapes included) to the others.
An effect is named only if it lowers the held-out torque error by at least MIN_IMPROVEMENT
against the plain refit; otherwise the answer is "none"."""

import math

import numpy as np

from model.effects import LIBRARY, Effect
from model.gap.candidates import Problem, Term, best_terms, solve
from model.gap.evidence import FOLDS

MIN_IMPROVEMENT = 0.10  # held-out torque RMSD must drop by 10 % to name an effect


def held_out_rmsd(problem: Problem, fixed: tuple[Term, ...], effect: Effect | None = None
                  ) -> float:
    """Torque RMSD on each time block when fitted on the others; `effect`'s shape is searched
    on the training blocks only."""
    folds = [f for f in range(FOLDS) if 0 < np.sum(problem.s.segment == f) < len(problem.s.t)]
    training = [problem.s.segment != f for f in folds]
    added = ([[]] * len(folds) if effect is None
             else [[term] for term in best_terms(problem, fixed, effect, training)])
    squared, count = 0.0, 0
    for rows, extra in zip(training, added, strict=True):
        test = ~rows
        fit = solve(problem, (*fixed, *extra), rows)
        residual = fit.predict(problem, test) - problem.target[test]
        squared += float(residual @ residual)
        count += int(test.sum())
    return math.sqrt(squared / count)


def bic(problem: Problem, terms: tuple[Term, ...]) -> float:
    fit = solve(problem, terms)
    residual = fit.predict(problem) - problem.target
    n = len(residual)
    k = len(fit.coefficients) + sum(term.effect.shape is not None for term in terms)
    return float(n * math.log(residual @ residual / n) + k * math.log(n))


def select(problem: Problem) -> tuple[tuple[Term, ...], dict]:
    """The effect with the lowest held-out error if it beats the plain refit by
    MIN_IMPROVEMENT (else none), and the score of every candidate."""
    baseline = held_out_rmsd(problem, ())
    candidates = {"none": {"held_out_rmsd": round(baseline, 5),
                           "bic": round(bic(problem, ()), 1)}}
    terms = {}
    for effect in LIBRARY:
        score = held_out_rmsd(problem, (), effect)
        terms[effect.name] = best_terms(problem, (), effect, [slice(None)])[0]
        candidates[effect.name] = {"held_out_rmsd": round(score, 5),
                                   "improvement": round(1 - score / baseline, 4),
                                   "bic": round(bic(problem, (terms[effect.name],)), 1),
                                   "shape": terms[effect.name].shape}
    best = min(terms, key=lambda n: candidates[n]["held_out_rmsd"])
    if candidates[best]["improvement"] >= MIN_IMPROVEMENT:
        return (terms[best],), candidates
    return (), candidates
