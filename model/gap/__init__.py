"""model-gap: where simulation and measurement disagree, which missing effects explain it, and
the model with them added.

One module per job: `evidence` (the recordings as rows, the model's predictions, residuals,
simulation error, where the residual lives), `candidates` (fits of the refit friction with
effects from the registry), `selection` (the held-out choice of effects), `discrimination`
(effects that explain the same residual: which the data support, what recording would tell),
`unexplained` (the structure no library effect explains, drift over time included, and a
data-driven correction for it), `instruments` (the motor side and the torque sensor each on
its own), `report` (the result and its JSON report). `find_gap` runs them in that order.
"""

from model.defaults import HORIZON
from model.gap.candidates import Problem, improved_parameters, solve
from model.gap.discrimination import discriminate
from model.gap.evidence import (
    collect,
    localise,
    residuals,
    rmsd,
    simulation_rmsd,
)
from model.gap.instruments import instruments
from model.gap.report import GapResult, build_report, improved_provenance, summary
from model.gap.selection import select
from model.gap.unexplained import unexplained
from model.identify import Experiment, IdentificationError
from model.parameters import ActuatorModel

__all__ = ["HORIZON", "GapError", "GapResult", "build_report", "find_gap",
           "improved_provenance", "summary"]

MISFIT = 0.25  # model torque error above 25 % of the measured torque: wrong model


class GapError(ValueError):
    """Data or model that model-gap cannot work with; the message says why."""


def find_gap(experiments: list[Experiment], model: ActuatorModel,
             horizon: float = HORIZON) -> GapResult:
    try:
        s = collect(experiments, model)
    except IdentificationError as exc:
        raise GapError(str(exc)) from None
    parameters = model.parameters
    residual_before, sensor_before = residuals(s, parameters)
    rmsd_before = rmsd(residual_before)
    scale = rmsd(s.motor_torque)
    if rmsd_before > MISFIT * scale:
        raise GapError(
            f"the model {model.source or model.name} does not fit these recordings: its torque "
            f"error is {rmsd_before:.2f} N.m, {100 * rmsd_before / scale:.0f} % of the measured "
            f"{scale:.2f} N.m (model-gap expects below {100 * MISFIT:.0f} %); identify a model "
            "for this actuator first")
    problem = Problem(s, parameters)
    selection = select(problem)
    terms = selection.terms
    fit = solve(problem, terms)
    improved = improved_parameters(fit, parameters) if terms else parameters
    structure, correction = unexplained(problem, problem.target - fit.predict(problem))
    residual_after, sensor_after = residuals(s, improved)
    ordered = residuals(problem.s, parameters)  # the problem's row order
    sim_before, traces_before = simulation_rmsd(experiments, parameters, horizon)
    sim_after, traces_after = simulation_rmsd(experiments, improved, horizon)
    return GapResult(
        effects=[term.effect.name for term in terms],
        rmsd_before=rmsd_before, rmsd_after=rmsd(residual_after),
        sim_rmsd_before=sim_before, sim_rmsd_after=sim_after,
        rmsd_sensor_before=rmsd(sensor_before), rmsd_sensor_after=rmsd(sensor_after),
        horizon=horizon, candidates=selection.candidates, steps=selection.steps,
        discrimination=[discriminate(problem, contest) for contest in selection.contests],
        instruments=instruments(problem, ordered[0], problem.target - fit.predict(problem),
                                ordered[1], bool(terms)),
        held_out_rmsd=selection.held_out_rmsd, unexplained=structure, correction=correction,
        parameters=improved,
        localisation_before=localise(s, residual_before, parameters),
        localisation_after=localise(s, residual_after, improved),
        residuals={"speed": s.qd, "position": s.q, "before": residual_before,
                   "after": residual_after},
        traces_before=traces_before, traces_after=traces_after)
