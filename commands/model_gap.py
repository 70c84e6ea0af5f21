"""`model-gap RECORDING... --model MODEL.toml`: where the model and the measurements disagree,
which missing effects explain it, what none explains, and the improved model."""

import datetime
import json
import sys
from pathlib import Path

from commands.file_options import check_distinct_outputs, check_output_file, check_output_folder
from commands.log_options import (
    add_logging_argument,
    configure_logging,
    job_error,
    reports_failures,
)
from commands.model_options import load_model_option
from commands.parsing import CommandParser, doc_description, positive_float, usage_error
from model.defaults import HORIZON

PROG = "model-gap"


def build_parser() -> CommandParser:
    parser = CommandParser(prog=PROG, description=doc_description(__doc__))
    parser.add_argument("recordings", nargs="+", metavar="RECORDING",
                        help="MCAP or CSV recordings (payload from their metadata, else none)")
    parser.add_argument("--model", required=True, metavar="MODEL.toml")
    parser.add_argument("--report", metavar="gap.json", help="write the JSON report here")
    parser.add_argument("--plots", metavar="DIR", help="before/after figures")
    parser.add_argument("-o", "--output", metavar="IMPROVED.toml",
                        help="write the improved model (only when effects are found)")
    parser.add_argument("--horizon", type=positive_float, default=HORIZON, metavar="S",
                        help="simulation horizon before restarting from the measured state, "
                             "0.01..10 (default: %(default)s s)")
    add_logging_argument(parser)
    return parser


@reports_failures(PROG)
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(PROG, args.log_level)
    # the numerical code once the arguments parsed: `--help` and a usage error answer
    # without importing scipy and numba
    from model.gap import GapError, build_report, find_gap, improved_provenance, summary
    from model.identify import Experiment
    from model.model_file import write_atomically, write_model
    from model.parameters import ModelFileError, Payload
    from model.plots import gap_figures
    from recorder.reader import load_recording
    from recorder.recording import RecordingError

    try:
        inputs = [("--model", args.model), *(("RECORDING", path) for path in args.recordings)]
        for option, path in (("--report", args.report), ("-o", args.output)):
            if path:
                check_output_file(option, path, inputs)
        check_distinct_outputs([("--report", args.report), ("-o", args.output)])
        if args.plots:
            check_output_folder("--plots", args.plots)
        model = load_model_option(args.model)
        experiments = []
        for path in args.recordings:
            recording = load_recording(path).with_joint_torque()
            experiments.append(Experiment(recording.t, recording.q, recording.current,
                                          recording.joint_torque,
                                          recording.payload() or Payload(), path))
        if not 0.01 <= args.horizon <= 10:
            raise ValueError(f"--horizon {args.horizon}: expected 0.01..10 s")
        result = find_gap(experiments, model, args.horizon)
    except (ModelFileError, RecordingError, GapError, ValueError) as exc:
        return usage_error(PROG, str(exc))

    improved_path = args.model
    option = "-o"
    try:  # a full disk: each file is written whole or not at all, named in one line
        if result.effects and args.output:
            provenance = improved_provenance(result, args.recordings,
                                             datetime.date.today().isoformat())
            write_model(Path(args.output), result.parameters, model,
                        f"{model.name or Path(args.model).stem} + {result.effect}", provenance)
            improved_path = args.output
        report = build_report(result, improved_path)
        if args.report:
            option = "--report"
            write_atomically(Path(args.report), json.dumps(report, indent=2).encode())
        if args.plots:
            option = "--plots"
            for path in gap_figures(result, Path(args.plots)):
                print(f"{PROG}: wrote {path}")
    except OSError as exc:
        shown = {"-o": args.output, "--report": args.report, "--plots": args.plots}[option]
        return job_error(PROG, f"{option} {shown}: cannot write: {exc.strerror or exc}")
    print(summary(result))
    closed = not result.effects or (result.rmsd_after < result.rmsd_before
                                    and result.sim_rmsd_after <= result.sim_rmsd_before)
    return 0 if closed else 1


if __name__ == "__main__":
    sys.exit(main())
