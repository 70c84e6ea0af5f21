"""model-gap on seeds the tests never draw (10-14) of their generator (tests/gap_case.py with
the parameter ranges of tests/test_gap_combinations.py): saturation alone and beside Stribeck
friction, warm-up friction alone (with the 20 s sinusoid), smooth reversal, clean data. Prints a
line per case: what was named, how much the torque and simulation gaps shrank, whether
anything was left unexplained or drifting, and the hidden truth. For the README's figures:

    python -m tests.gap_fresh_seeds DIR        (DIR keeps the recordings and reports)
"""

import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from tests.test_gap_combinations import case_id, options, truth

SEEDS = range(10, 15)
CASES = ([(("torque_constant_saturation",), s, "elbow") for s in SEEDS]
         + [(("stribeck", "torque_constant_saturation"), s, "elbow") for s in SEEDS]
         + [(("warm_up_friction",), s, "elbow") for s in SEEDS]
         + [(("smooth_reversal",), s, "elbow") for s in SEEDS]
         + [((), s, "elbow") for s in SEEDS])


def run(root: Path, share: list[tuple], k: int) -> None:
    items = []
    for case in share:
        folder = root / case_id(case)
        folder.mkdir(exist_ok=True)
        items.append([str(folder), case[1], truth(*case), *options(case, {})])
    cases = root / f"cases{k}.json"
    cases.write_text(json.dumps(items))
    subprocess.run([sys.executable, "-m", "tests.gap_case", str(cases)], capture_output=True,
                   check=True)


def main(root: Path) -> None:
    root.mkdir(exist_ok=True)
    with ThreadPoolExecutor(2) as pool:
        list(pool.map(run, [root, root], [CASES[0::2], CASES[1::2]], [0, 1]))
    for case in CASES:
        folder = root / case_id(case)
        if not (folder / "gap.json").exists():
            print(f"{case_id(case):40s} ERROR {(folder / 'error.txt').read_text()[-300:]}")
            continue
        r = json.loads((folder / "gap.json").read_text())
        drift = r["unexplained"]["drift"]
        print(f"{case_id(case):40s} {r['effect']:37s} torque gap -"
              f"{100 * (1 - r['rmsd_after'] / r['rmsd_before']):.0f} %, simulation -"
              f"{100 * (1 - r['sim_rmsd_after'] / r['sim_rmsd_before']):.0f} %, unexplained "
              f"{r['unexplained']['found']}, drift {drift['found']} "
              f"(tau {drift['time_constant_range_s'][0]:g}-{drift['time_constant_range_s'][1]:g}"
              f" s); hidden {' '.join(truth(*case)) or 'nothing'}")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
