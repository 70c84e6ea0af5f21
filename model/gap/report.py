"""What model-gap tells its user: the result of a run and the JSON report built from it (the
contract keys `effect`, `rmsd_before`, `rmsd_after`, `sim_rmsd_before`, `sim_rmsd_after`,
`model`, and the evidence behind the choice)."""

from dataclasses import dataclass

from model.effects import EFFECTS
from model.gap.evidence import FOLDS
from model.gap.selection import MIN_IMPROVEMENT
from model.parameters import ActuatorParameters


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


def build_report(result: GapResult, model_path: str) -> dict:
    effect_parameters = ({} if result.effect == "none"
                         else result.parameters.effects.section(result.effect))
    return {
        "effect": result.effect,
        "rmsd_before": result.rmsd_before,
        "rmsd_after": result.rmsd_after,
        "sim_rmsd_before": result.sim_rmsd_before,
        "sim_rmsd_after": result.sim_rmsd_after,
        "model": str(model_path),
        "rmsd_signal": "motor torque at joint level (drive_gain x current) against the model's "
                       "inverse dynamics, N.m",
        "rmsd_sensor_before": result.rmsd_sensor_before,
        "rmsd_sensor_after": result.rmsd_sensor_after,
        "sim_horizon_s": result.horizon,
        "effect_parameters": effect_parameters,
        "effect_units": EFFECTS[result.effect].units if result.effect in EFFECTS else {},
        "candidates": result.candidates,
        "selection": f"lowest held-out torque RMSD over {FOLDS} contiguous time blocks; named "
                     f"only if it beats the plain refit by >= {100 * MIN_IMPROVEMENT:.0f} %",
        "where_before": result.localisation_before,
        "where_after": result.localisation_after,
    }
