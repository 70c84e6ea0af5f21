"""`identify NOLOAD LOAD`: the actuator model from two recordings (MCAP or CSV), by the
paper's total least squares, written as a model TOML that sim-bus, actuatord and model-gap
accept."""

from __future__ import annotations

import datetime
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from commands.file_options import check_output_file, check_output_folder
from commands.log_options import (
    add_logging_argument,
    configure_logging,
    job_error,
    reports_failures,
)
from commands.model_options import (
    add_model_argument,
    add_payload_arguments,
    load_model_option,
    parse_payload,
)
from commands.parsing import CommandParser, doc_description, positive_float, usage_error
from model.defaults import CUTOFF_HZ

if TYPE_CHECKING:
    from model.identify import Experiment, Identified
    from model.parameters import ActuatorModel
    from recorder.recording import Recording

PROG = "identify"


def build_parser() -> CommandParser:
    parser = CommandParser(prog=PROG, description=doc_description(__doc__))
    parser.add_argument("no_load", metavar="NOLOAD", help="recording without payload")
    parser.add_argument("load", metavar="LOAD", help="recording with the known payload")
    add_payload_arguments(parser, mass_default=None,
                          mass_help="payload of LOAD (kg; default: from LOAD's metadata)")
    parser.add_argument("-o", "--output", required=True, metavar="MODEL.toml")
    add_model_argument(parser, help="nominal model: limits, the defaults shown beside the "
                                    "identified values, and drive-side effects to keep (e.g. "
                                    "torque_constant_saturation found by model-gap; default: "
                                    "packaged)")
    parser.add_argument("--cutoff", type=positive_float, default=CUTOFF_HZ, metavar="HZ",
                        help="zero-phase low-pass cutoff, below the recordings' Nyquist "
                             "frequency (default: %(default)s Hz)")
    parser.add_argument("--plots", metavar="DIR", help="save measured vs predicted torques")
    add_logging_argument(parser)
    return parser


def _experiment(recording: Recording, payload) -> Experiment:
    from model.identify import Experiment

    recording.with_joint_torque()
    return Experiment(recording.t, recording.q, recording.current, recording.joint_torque,
                      payload, recording.source)


@reports_failures(PROG)
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(PROG, args.log_level)
    # the numerical code once the arguments parsed: `--help` and a usage error answer
    # without importing scipy and numba
    from model.identify import IdentificationError, identify
    from model.parameters import ModelFileError
    from recorder.reader import load_recording
    from recorder.recording import RecordingError

    try:
        check_output_file("-o", args.output, [("NOLOAD", args.no_load), ("LOAD", args.load),
                                              ("--model", args.model)])
        if args.plots:
            check_output_folder("--plots", args.plots)
        nominal = load_model_option(args.model)
        no_load = load_recording(args.no_load)
        load = load_recording(args.load)
        if args.payload_mass is not None:
            payload = parse_payload(args.payload_mass, args.payload_position)
        else:
            payload = load.payload()
            if payload is None:
                raise ValueError(f"{args.load}: no payload given: use --payload-mass and "
                                 "--payload-position, or record with them (metadata)")
        no_load_payload = no_load.payload() or parse_payload(0.0, None)
        result = identify(_experiment(no_load, no_load_payload), _experiment(load, payload),
                          args.cutoff, nominal.parameters.effects)
    except (ModelFileError, RecordingError, IdentificationError, ValueError) as exc:
        return usage_error(PROG, str(exc))
    try:
        write_identified(Path(args.output), result, nominal, args.no_load, args.load)
    except OSError as exc:  # a full disk: the model is written whole or not at all
        return job_error(PROG, f"-o {args.output}: cannot write: {exc.strerror or exc}")
    print(table(result, nominal))
    print(f"condition number {result.condition_number:.1f} (paper: 36); torque-fit RMSD motor "
          f"{result.rmsd_motor:.3f} N.m, joint {result.rmsd_joint:.3f} N.m (paper: 0.6 N.m); "
          f"{result.rows} rows -> {args.output}")
    if args.plots:
        from model.plots import identification_figures

        try:
            for path in identification_figures(result, Path(args.plots)):
                print(f"{PROG}: wrote {path}")
        except OSError as exc:
            return job_error(PROG, f"--plots {args.plots}: cannot write: "
                                   f"{exc.strerror or exc} (the model was written)")
    return 0


def table(result: Identified, nominal: ActuatorModel) -> str:
    from model.identify import PARAMETERS

    lines = [f"{'parameter':26s} {'default':>9s} {'identified':>11s} {'rel. std':>9s}"]
    for name in PARAMETERS:
        lines.append(f"{name:26s} {getattr(nominal.parameters, name):9.4f} "
                     f"{getattr(result.parameters, name):11.4f} "
                     f"{result.relative_std[name]:8.2f}%")
    return "\n".join(lines)


def write_identified(path: Path, result: Identified, nominal: ActuatorModel, no_load: str,
                     load: str) -> None:
    from model.identify import PARAMETERS
    from model.model_file import write_model

    date = datetime.date.today().isoformat()
    origin = (f"identified from {no_load} and {load} on {date} (total least squares, "
              f"condition number {result.condition_number:.1f})")
    write_model(path, result.parameters, nominal,
                f"identified from {Path(no_load).name} and {Path(load).name}",
                {name: origin for name in PARAMETERS}, result.std)


if __name__ == "__main__":
    sys.exit(main())
