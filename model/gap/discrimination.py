"""When two effects explain the same residual: where their predictions part, whether these
recordings tell them apart, and what recording would.

Effects that explain one residual differ somewhere else. Load-dependent friction opposes the
motion, so it adds current when the drive moves the load and takes current away when the
drive brakes it; a saturating torque constant needs more current whatever the motion. The
rows are split by power flow (motoring: the current along the motion; braking: against it)
and by gravity load (above or below its median), and each fit's prediction compared there:
the region where they part most is what a recording must contain to tell them apart.

The verdict uses the selection's own yardstick: the data support the winner when its held-out
error is at least MIN_IMPROVEMENT below the rival's (what an effect needs to join at all);
otherwise the report says these recordings cannot tell the two apart (the winner is kept for
its lower error) and names the recording that would.
"""

import numpy as np

from model.gap.candidates import Problem, solve
from model.gap.evidence import gravity, rmsd
from model.gap.selection import MIN_IMPROVEMENT, Contest

MIN_REGION_SHARE = 0.05  # a region with fewer of the rows is "barely in these recordings"


def _regions(problem: Problem) -> list[tuple[str, np.ndarray]]:
    s = problem.s
    load = np.abs(gravity(s, problem.parameters)[0])
    median = float(np.median(load))
    flow = s.current * s.qd
    out = []
    for flow_name, moving in (("motoring (current along the motion)", flow > 0),
                              ("braking (current against the motion)", flow < 0)):
        for load_name, loaded in ((f"at high load (|G| above {median:.3g} N.m)", load > median),
                                  (f"at low load (|G| below {median:.3g} N.m)", load <= median)):
            out.append((f"{flow_name} {load_name}", moving & loaded))
    return out


def discriminate(problem: Problem, contest: Contest) -> dict:
    """The report on one contest (see the module docstring)."""
    winner, rival = contest.winner.effect, contest.rival.effect
    difference = (solve(problem, (*contest.fixed, contest.winner)).predict(problem)
                  - solve(problem, (*contest.fixed, contest.rival)).predict(problem))
    regions = [{"region": name, "samples": int(inside.sum()),
                "difference_rmsd_nm": round(rmsd(difference[inside]), 5) if inside.any()
                else 0.0}
               for name, inside in _regions(problem)]
    widest = max(regions, key=lambda r: r["difference_rmsd_nm"])
    share = widest["samples"] / len(difference)
    supported = contest.winner_rmsd <= (1 - MIN_IMPROVEMENT) * contest.rival_rmsd
    held_out = (f"held-out torque RMSD {contest.winner_rmsd:.4f} N.m with {winner.name}, "
                f"{contest.rival_rmsd:.4f} with {rival.name}, {contest.before:.4f} with neither")
    if supported:
        says = f"the data support {winner.name} over {rival.name} ({held_out})"
    else:
        says = (f"these recordings cannot tell {winner.name} from {rival.name} ({held_out}); "
                f"{winner.name} is kept for its lower error")
    where = widest["region"] + (f", barely in these recordings ({100 * share:.1f} % of the rows)"
                                if share < MIN_REGION_SHARE else "")
    return {
        "effects": [winner.name, rival.name],
        "with": [term.effect.name for term in contest.fixed],
        "held_out_rmsd": {winner.name: round(contest.winner_rmsd, 5),
                          rival.name: round(contest.rival_rmsd, 5),
                          "neither": round(contest.before, 5)},
        "verdict": "supported" if supported else "undecided",
        "chosen": winner.name,
        "says": says,
        "they_differ_most": widest,
        "regions": regions,
        "recording_that_would_tell_them_apart": (
            f"more {where}, where the two fits part most; {winner.name}: {winner.reveals}; "
            f"{rival.name}: {rival.reveals}"),
    }
