"""The choice of effects, made on held-out data: each recording is cut into FOLDS contiguous
time blocks and each block is predicted by a fit (shapes included) to the others.

Forward selection over the library: at each step every effect not yet chosen is fitted
together with those chosen; the one with the lowest held-out torque error joins them only if
it lowers that error by at least MIN_IMPROVEMENT, and only if the joint fit is physically
plausible for every effect in it (each effect's constraints in `model.effects`: a Stribeck
"breakaway" below the Coulomb level is not Stribeck friction). Clean data gives no effect.
Every other plausible effect that would have joined at that step too (it alone lowers the
error by MIN_IMPROVEMENT) and does not join later is a rival explanation of the same residual:
`Selection.contests` keeps them for `model.gap.discrimination`.
"""

import math
from dataclasses import dataclass

import numpy as np

from model.effects import EFFECTS, LIBRARY, Effect, FitContext
from model.gap.candidates import REFIT, Fit, Problem, Term, best_terms, solve
from model.gap.evidence import FOLDS

MIN_IMPROVEMENT = 0.10  # held-out torque RMSD must drop by 10 % for an effect to join


def held_out_rmsd(problem: Problem, fixed: tuple[Term, ...],
                  added: list[Term] | None = None) -> float:
    """Torque RMSD on each time block when fitted on the others; `added[fold]` is the term
    (shape searched on that fold's training blocks only) that joins `fixed` for it."""
    squared, count = 0.0, 0
    for fold, rows in enumerate(problem.blocks):
        if rows.stop - rows.start in (0, len(problem.target)):
            continue
        training = np.ones(len(problem.target), bool)
        training[rows] = False
        terms = (*fixed, added[fold]) if added else fixed
        residual = solve(problem, terms, training).predict(problem, rows) - problem.target[rows]
        squared += float(residual @ residual)
        count += rows.stop - rows.start
    return math.sqrt(squared / count)


def violations(problem: Problem, fit: Fit) -> dict[str, list[str]]:
    """Each fitted effect's broken constraints (only effects that break any)."""
    coulomb = fit.coefficients[REFIT.index("dry_friction_motor")] + (
        problem.parameters.dry_friction_joint)
    context = FitContext(coulomb=float(coulomb), position_range=float(np.ptp(problem.s.q)),
                         current_peak=float(np.max(np.abs(problem.s.current))))
    out = {}
    for name, table in fit.tables().items():
        broken = EFFECTS[name].violations(table, context)
        if broken:
            out[name] = broken
    return out


@dataclass(frozen=True)
class Contest:
    """Two effects that each explain the residual left by `fixed`: `winner` joined."""

    fixed: tuple[Term, ...]
    winner: Term
    rival: Term
    before: float  # held-out RMSD with `fixed` alone
    winner_rmsd: float  # ... with the winner added
    rival_rmsd: float  # ... with the rival added instead


@dataclass
class Selection:
    terms: tuple[Term, ...]
    held_out_rmsd: float  # of the chosen set
    candidates: dict  # every effect as last considered, and "none"
    steps: list[dict]  # what joined, in order, and the held-out error it brought
    contests: list[Contest]  # rivals of each effect that joined (that never joined)


def select(problem: Problem) -> Selection:
    chosen: tuple[Term, ...] = ()
    current = held_out_rmsd(problem, ())
    candidates: dict = {"none": {"held_out_rmsd": round(current, 5)}}
    steps: list[dict] = []
    contests: list[Contest] = []
    while len(chosen) < len(LIBRARY):
        best = None
        tried: list[tuple[float, Term]] = []  # the plausible ones
        for effect in LIBRARY:
            if any(term.effect is effect for term in chosen):
                continue
            *per_fold, term = best_terms(problem, chosen, effect, [*range(FOLDS), None])
            broken = violations(problem, solve(problem, (*chosen, term)))
            score = held_out_rmsd(problem, chosen, per_fold)
            candidates[effect.name] = {
                "with": [t.effect.name for t in chosen], "held_out_rmsd": round(score, 5),
                "improvement": round(1 - score / current, 4), "shape": term.shape,
                "plausible": not broken, "violations": broken}
            if not broken:
                tried.append((score, term))
                if best is None or score < best[0]:
                    best = (score, term)
        if best is None or 1 - best[0] / current < MIN_IMPROVEMENT:
            break
        contests += [Contest(chosen, best[1], term, current, best[0], score)
                     for score, term in tried
                     if term is not best[1] and 1 - score / current >= MIN_IMPROVEMENT]
        chosen, current = (*chosen, best[1]), best[0]
        steps.append({"added": best[1].effect.name, "held_out_rmsd": round(current, 5),
                      "plausible_tried": {term.effect.name: round(score, 5)
                                          for score, term in tried}})
    joined = {term.effect.name for term in chosen}
    return Selection(_reshaped(problem, chosen), current, candidates, steps,
                     [c for c in contests if c.rival.effect.name not in joined])


def contest(problem: Problem, fixed: tuple[Term, ...], winner: Effect, rival: Effect
            ) -> Contest:
    """Two effects weighed against each other beside `fixed`, each shaped on the data, with
    the held-out errors the selection would give them (for a pair the user names)."""
    scores = []
    terms = []
    for effect in (winner, rival):
        *per_fold, term = best_terms(problem, fixed, effect, [*range(FOLDS), None])
        scores.append(held_out_rmsd(problem, fixed, per_fold))
        terms.append(term)
    return Contest(fixed, terms[0], terms[1], held_out_rmsd(problem, fixed), *scores)


def _reshaped(problem: Problem, terms: tuple[Term, ...]) -> tuple[Term, ...]:
    """Each chosen effect's shape searched again with all the others in the fit (an effect
    found first was shaped while the later ones were still missing); kept only if the joint
    fit stays plausible."""
    reshaped = list(terms)
    for i, term in enumerate(reshaped):
        others = tuple(reshaped[:i] + reshaped[i + 1:])
        reshaped[i] = best_terms(problem, others, term.effect, [None])[0]
    if violations(problem, solve(problem, tuple(reshaped))):
        return terms
    return tuple(reshaped)
