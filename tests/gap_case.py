"""model-gap cases, one after the other in one process (python -m tests.gap_case CASES.json,
a list of [DIR, SEED, [TRUTH, ...]], optionally followed by MODEL.toml (or null) and the
seconds of a slow sinusoid): per case, two short exciting trajectories recorded in lock-step
on the virtual drive (the packaged elbow, or MODEL) carrying the hidden truth (without and with
5 kg at (0, 0.1) m), a baseline identified from them, and model-gap's report on them (and on
the sinusoid, when asked: a recording whose speeds do not change with time, long enough for a
drift) in DIR/gap.json (or what went wrong in DIR/error.txt). One process for many cases pays
the imports and the compiled code once."""

import contextlib
import io
import json
import sys
import traceback
from pathlib import Path

from commands import identify, model_gap
from commands import recorder as cli

# 9.5 s each: two cruise speeds over the whole range, both directions
TRAJECTORY = ["--velocity-min", "1.0", "--velocity-max", "2.4", "--steps", "2"]


def main(argv: list[str]) -> int:
    for folder, seed, truths, *options in json.loads(Path(argv[0]).read_text()):
        errors = io.StringIO()
        try:
            with contextlib.redirect_stderr(errors):
                code = run_case(Path(folder), seed, truths, *options)
        except Exception:
            code, errors = 1, io.StringIO(traceback.format_exc())
        if code:
            Path(folder, "error.txt").write_text(f"exit {code}: {errors.getvalue()}")
    return 0


def run_case(folder: Path, seed: int, truths: list[str], model: str | None = None,
             sinusoid: float = 0.0) -> int:
    hidden = [arg for truth in truths for arg in ("--truth-effect", truth)]
    nominal = ["--model", model] if model else []
    files = {name: str(folder / f"{name}.mcap") for name in ("noload", "load")}
    common = ["--exciting-trajectory", "--sim", "--lockstep", "--no-progress", *TRAJECTORY,
              *hidden, *nominal]
    for name, noise_seed, extra in (
            ("noload", 2 * int(seed), []),
            ("load", 2 * int(seed) + 1, ["--payload-mass", "5", "--payload-position", "0,0.1"])):
        code = cli.main([*common, *extra, "--seed", str(noise_seed), "-o", files[name]])
        if code:
            return code
    baseline = str(folder / "baseline.toml")
    code = identify.main([files["noload"], files["load"], "-o", baseline, *nominal])
    if code:
        return code
    recordings = [files["noload"], files["load"]]
    if sinusoid:
        recordings.append(str(folder / "sinusoid.mcap"))
        code = cli.main(["--sinusoid", "--sim", "--lockstep", "--no-progress", *hidden,
                         *nominal, "--duration", str(sinusoid), "--seed",
                         str(2 * int(seed) + 2), "-o", recordings[-1]])
        if code:
            return code
    return model_gap.main([*recordings, "--model", baseline, "--report",
                           str(folder / "gap.json")])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
