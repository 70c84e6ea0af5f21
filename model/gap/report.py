"""What model-gap tells its user: the result of a run and the JSON report built from it (the
contract keys `effect`, `rmsd_before`, `rmsd_after`, `sim_rmsd_before`, `sim_rmsd_after`,
`model`, and the evidence behind the choice)."""

from dataclasses import dataclass

from model.effects import EFFECTS
from model.gap.candidates import REFIT
from model.gap.evidence import FOLDS
from model.gap.selection import MIN_IMPROVEMENT
from model.parameters import ActuatorParameters


@dataclass
class GapResult:
    effects: list[str]  # the effects found, in the order they joined ([] on clean data)
    rmsd_before: float
    rmsd_after: float
    sim_rmsd_before: float
    sim_rmsd_after: float
    rmsd_sensor_before: float
    rmsd_sensor_after: float
    horizon: float
    candidates: dict
    steps: list[dict]  # the forward selection: what joined and the held-out error after it
    discrimination: list[dict]  # effects that explained the same residual as one that joined
    instruments: dict  # the motor side and the torque sensor, each on its own
    held_out_rmsd: float  # of the chosen effects (N.m)
    unexplained: dict  # structure left in the residual, and where
    correction: dict | None  # data-driven map for it (never a named effect), if any
    parameters: ActuatorParameters  # improved (or unchanged when no effect is found)
    localisation_before: dict
    localisation_after: dict
    residuals: dict  # for plots: speed, position, before, after
    traces_before: list
    traces_after: list

    @property
    def effect(self) -> str:
        """The effects' names joined by "+", or "none"."""
        return "+".join(self.effects) or "none"


def build_report(result: GapResult, model_path: str) -> dict:
    return {
        "effect": result.effect,
        "effects": result.effects,
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
        "effect_parameters": {name: result.parameters.effects.section(name)
                              for name in result.effects},
        "effect_units": {name: EFFECTS[name].units for name in result.effects},
        "held_out_rmsd": result.held_out_rmsd,
        "candidates": result.candidates,
        "steps": result.steps,
        "discrimination": result.discrimination,
        "unexplained": result.unexplained,
        "correction": result.correction,
        "instruments": result.instruments,
        "selection": f"forward selection on the held-out torque RMSD over {FOLDS} contiguous "
                     "time blocks: an effect joins only if it lowers it by >= "
                     f"{100 * MIN_IMPROVEMENT:.0f} % and every fitted effect stays plausible",
        "where_before": result.localisation_before,
        "where_after": result.localisation_after,
    }


def improved_provenance(result: GapResult, sources: list[str], date: str) -> dict[str, str]:
    """Where each number model-gap changed comes from, for the improved model file."""
    origin = f"model-gap on {', '.join(sources)} ({date})"
    note = (f"{origin}: held-out torque RMSD {result.held_out_rmsd:.4f} vs "
            f"{result.candidates['none']['held_out_rmsd']:.4f} N.m without {result.effect}")
    return {**{f"effects.{name}": note for name in result.effects},
            **{name: f"refitted with {result.effect} by {origin}"
               for name in (*REFIT, "drive_gain")}}


def summary(result: GapResult) -> str:
    """A few lines for the terminal."""
    lines = [f"effect: {result.effect}",
             f"torque RMSD {result.rmsd_before:.4f} -> {result.rmsd_after:.4f} N.m; simulated "
             f"position RMSD ({result.horizon} s horizon) {result.sim_rmsd_before:.5f} -> "
             f"{result.sim_rmsd_after:.5f} rad",
             "held-out torque RMSD per candidate (last step it was tried): " + ", ".join(
                 f"{name} {c['held_out_rmsd']:.4f}"
                 + ("" if c.get("plausible", True) else " (implausible)")
                 for name, c in result.candidates.items())]
    worst = max(result.localisation_before["by_speed_rad_s"], key=lambda b: b["rmsd"])
    lines.append(f"largest disagreement before: |qd| in [{worst['from']}, {worst['to']}) "
                 f"rad/s, {worst['rmsd']:.3f} N.m")
    for contest in result.discrimination:
        if contest["verdict"] == "supported":
            lines.append(f"{contest['says']}; their fits part most "
                         f"{contest['they_differ_most']['region']}")
        else:
            lines.append(f"{contest['says']}; to tell them apart record "
                         f"{contest['recording_that_would_tell_them_apart']}")
    for place in result.unexplained["where"]:
        bins = ", ".join(f"[{b['from']}, {b['to']}) mean {b['mean']:+.3f} N.m"
                         for b in place["bins"])
        lines.append(f"unexplained by the library: along {place['axis']} (a map lowers the "
                     f"held-out error by {100 * place['gain']:.0f} %): {bins}")
    drift = result.unexplained["drift"]
    if drift["found"]:
        low, high = drift["time_constant_range_s"]
        lines.append(f"unexplained drift over each recording: a {drift['kind']} decaying by "
                     f"{drift['decay_over_longest_recording_nm']:+.3f} N.m over "
                     f"{drift['longest_recording_s']:g} s, time constant {low:g}-{high:g} s"
                     + (" or longer (record longer to bound it)"
                        if drift["slower_than_the_recordings"] else ""))
    lines.append(f"instruments: {result.instruments['verdict_before']}")
    return "\n".join(lines)
