"""model-gap on harder data: every pair of library effects hidden together, an effect outside
the library, and clean data. Each effect's parameters are drawn at random within the stated
ranges (three seeds per case); each case is recorded once on the virtual drive in lock-step
(tests/gap_case.py, two processes sharing the cases) and its report shared by the tests."""

import itertools
import json
import math
import random
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest

from model.effects import HIDDEN_ONLY, LIBRARY, LIBRARY_NAMES

# the ranges the hidden parameters are drawn from (uniform)
RANGES = {
    "stribeck": {"breakaway_friction": (1.0, 2.0), "velocity": (0.03, 0.08)},
    "position_ripple": {"amplitude": (0.3, 0.8), "spatial_frequency": (3.0, 12.0),
                        "phase": (-math.pi, math.pi)},
    "load_dependent_friction": {"coefficient": (0.06, 0.15)},
    "friction_ripple": {"amplitude": (0.3, 0.7), "spatial_frequency": (3.0, 12.0),
                        "phase": (-math.pi, math.pi)},
    # outside the library: dry friction reversing smoothly over 8-15 mrad/s instead of sticking
    "smooth_reversal": {"velocity": (0.008, 0.015)},
}
SEEDS = (0, 1, 2)
PAIRS = list(itertools.combinations(LIBRARY_NAMES, 2))
NEW = ("friction_ripple",)  # library effects with no single-effect case in test_model_gap.py
CASES = ([(pair, seed) for pair in PAIRS for seed in SEEDS]
         + [((name,), seed) for name in NEW for seed in SEEDS]
         + [(("smooth_reversal",), seed) for seed in SEEDS] + [((), 0)])


def truth(effects: tuple[str, ...], seed: int) -> list[str]:
    rng = random.Random(f"{'+'.join(effects)}:{seed}")
    return [f"{name}:" + ",".join(f"{key}={rng.uniform(*bounds):.4g}"
                                  for key, bounds in RANGES[name].items())
            for name in effects]


def case_id(case: tuple) -> str:
    effects, seed = case
    return f"{'+'.join(effects) or 'clean'}-{seed}"


# the first test pays for every case's recordings (about 30 cases, two at a time): longer
# than the suite's 300 s per-test default even on a quiet machine
pytestmark = [pytest.mark.timeout(1800), pytest.mark.subprocess]


@pytest.fixture(scope="session")
def reports(tmp_path_factory) -> dict[str, dict | str]:
    """Each case's report, or why the case could not run (each test checks its own). Two
    processes (two cores) share the cases, each paying the imports once."""
    folders = {case_id(case): tmp_path_factory.mktemp(case_id(case)) for case in CASES}

    def run(share: list[tuple]) -> None:
        cases = tmp_path_factory.mktemp("cases") / "cases.json"
        cases.write_text(json.dumps([[str(folders[case_id(case)]), case[1], truth(*case)]
                                     for case in share]))
        subprocess.run([sys.executable, "-m", "tests.gap_case", str(cases)],
                       capture_output=True, text=True, timeout=1500)

    with ThreadPoolExecutor(2) as pool:
        list(pool.map(run, [CASES[0::2], CASES[1::2]]))
    out: dict[str, dict | str] = {}
    for name, folder in folders.items():
        report, error = folder / "gap.json", folder / "error.txt"
        out[name] = (json.loads(report.read_text()) if report.exists() else
                     error.read_text() if error.exists() else "the case did not run")
    return out


def report_of(reports: dict, case: tuple) -> dict:
    report = reports[case_id(case)]
    assert isinstance(report, dict), report
    return report


def test_the_library_covers_every_pair_and_the_outside_effect_is_not_in_it():
    assert set(RANGES) == set(LIBRARY_NAMES) | {effect.name for effect in HIDDEN_ONLY}
    assert "smooth_reversal" not in LIBRARY_NAMES
    assert len(PAIRS) == len(LIBRARY) * (len(LIBRARY) - 1) // 2


@pytest.mark.parametrize("case", [c for c in CASES if len(c[0]) == 2], ids=case_id)
def test_a_hidden_pair_is_named_exactly_and_both_gaps_shrink(reports, case):
    report = report_of(reports, case)
    assert sorted(report["effects"]) == sorted(case[0]), (truth(*case), report["candidates"])
    assert report["effect"] == "+".join(report["effects"])
    assert report["rmsd_after"] <= 0.6 * report["rmsd_before"]
    assert report["sim_rmsd_after"] <= 0.6 * report["sim_rmsd_before"]


@pytest.mark.parametrize("case", [c for c in CASES if len(c[0]) == 1 and c[0][0] in NEW],
                         ids=case_id)
def test_a_new_library_effect_hidden_alone_is_named_and_comes_back(reports, case):
    report = report_of(reports, case)
    assert report["effects"] == list(case[0])
    assert report["rmsd_after"] <= 0.6 * report["rmsd_before"]
    assert report["sim_rmsd_after"] <= 0.6 * report["sim_rmsd_before"]
    hidden = dict(item.split("=") for item in truth(*case)[0].split(":")[1].split(","))
    found = report["effect_parameters"][case[0][0]]
    assert found["spatial_frequency"] == pytest.approx(float(hidden["spatial_frequency"]),
                                                       abs=0.1)
    assert found["amplitude"] == pytest.approx(float(hidden["amplitude"]), rel=0.15)


@pytest.mark.parametrize("case", [c for c in CASES if c[0] == ("smooth_reversal",)],
                         ids=case_id)
def test_an_effect_outside_the_library_is_not_named_but_located(reports, case):
    report = report_of(reports, case)
    assert report["effects"] == [] and report["effect"] == "none"
    assert set(report["candidates"]) == {"none", *LIBRARY_NAMES}
    # a Stribeck fit would need a breakaway below the Coulomb level: refused, not named
    assert not report["candidates"]["stribeck"]["plausible"]
    where = report["unexplained"]
    assert where["found"]
    assert where["where"][0]["axis"] == "velocity_rad_s"
    for band in where["where"][0]["bins"]:  # the reversal region, not the cruise speeds
        assert max(abs(band["from"]), abs(band["to"])) <= 0.04, band
    correction = report["correction"]
    assert "not a physical effect" in correction["kind"]
    assert correction["held_out_rmsd_with"] <= 0.6 * correction["rmsd_without"]


def test_clean_data_gives_no_effect_and_no_unexplained_structure(reports):
    report = report_of(reports, ((), 0))
    assert report["effects"] == [] and report["effect"] == "none"
    assert report["rmsd_after"] == report["rmsd_before"]
    assert not report["unexplained"]["found"] and report["correction"] is None
