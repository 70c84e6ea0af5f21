"""`model-gap RECORDING... --model MODEL.toml`: where the model and the measurements disagree,
which missing effect explains it, and the improved model."""

import datetime
import json
import sys
from pathlib import Path

import numpy as np

from commands.options import (
    CommandParser,
    add_logging_argument,
    check_output_file,
    check_output_folder,
    configure_logging,
    positive_float,
    read_recording,
    usage_error,
)
from model.effects import EFFECT_KEYS
from model.gap import GapError, GapResult, find_gap
from model.identify import Experiment
from model.model_file import write_model
from model.parameters import ModelFileError, Payload, load_model
from recorder.recording import RecordingError

PROG = "model-gap"


def build_parser() -> CommandParser:
    parser = CommandParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument("recordings", nargs="+", metavar="RECORDING",
                        help="MCAP or CSV recordings (payload from their metadata, else none)")
    parser.add_argument("--model", required=True, metavar="MODEL.toml")
    parser.add_argument("--report", metavar="gap.json", help="write the JSON report here")
    parser.add_argument("--plots", metavar="DIR", help="before/after figures")
    parser.add_argument("-o", "--output", metavar="IMPROVED.toml",
                        help="write the improved model (only when an effect is found)")
    parser.add_argument("--horizon", type=positive_float, default=0.5, metavar="S",
                        help="simulation horizon before restarting from the measured state, "
                             "0.01..10 (default: %(default)s s)")
    add_logging_argument(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(PROG, args.log_level)
    try:
        for option, path in (("--report", args.report), ("-o", args.output)):
            if path:
                check_output_file(option, path)
        if args.plots:
            check_output_folder("--plots", args.plots)
        model = load_model(args.model)
        experiments = []
        for path in args.recordings:
            recording = read_recording(path)
            experiments.append(Experiment(recording.t, recording.q, recording.current,
                                          recording.joint_torque,
                                          recording.payload() or Payload(), path))
        if not 0.01 <= args.horizon <= 10:
            raise ValueError(f"--horizon {args.horizon}: expected 0.01..10 s")
        result = find_gap(experiments, model, args.horizon)
    except (ModelFileError, RecordingError, GapError, ValueError) as exc:
        return usage_error(PROG, str(exc))

    improved_path = args.model
    if result.effect != "none" and args.output:
        date = datetime.date.today().isoformat()
        sources = ", ".join(args.recordings)
        note = (f"model-gap on {sources} ({date}): held-out torque RMSD "
                f"{result.candidates[result.effect]['held_out_rmsd']:.4f} vs "
                f"{result.candidates['none']['held_out_rmsd']:.4f} N.m without it")
        provenance = {f"effects.{result.effect}": note,
                      **{name: f"refitted with {result.effect} by model-gap on {sources} "
                               f"({date})"
                         for name in ("viscous_friction_motor", "dry_friction_motor",
                                      "torque_offset_motor")}}
        write_model(Path(args.output), result.parameters, model,
                    f"{model.name or Path(args.model).stem} + {result.effect}", provenance)
        improved_path = args.output
    report = build_report(result, improved_path)
    if args.report:
        Path(args.report).write_text(json.dumps(report, indent=2))
    if args.plots:
        for path in save_plots(result, Path(args.plots)):
            print(f"model-gap: wrote {path}")
    print(summary(result))
    closed = result.effect == "none" or (result.rmsd_after < result.rmsd_before
                                         and result.sim_rmsd_after <= result.sim_rmsd_before)
    return 0 if closed else 1


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
        "effect_units": {k: unit for k, (_, unit) in EFFECT_KEYS.get(result.effect, {}).items()},
        "candidates": result.candidates,
        "selection": "lowest held-out torque RMSD over 5 contiguous time blocks; named only if "
                     "it beats the plain refit by >= 10 %",
        "where_before": result.localisation_before,
        "where_after": result.localisation_after,
    }


def summary(result: GapResult) -> str:
    lines = [f"effect: {result.effect}",
             f"torque RMSD {result.rmsd_before:.4f} -> {result.rmsd_after:.4f} N.m; simulated "
             f"position RMSD ({result.horizon} s horizon) {result.sim_rmsd_before:.5f} -> "
             f"{result.sim_rmsd_after:.5f} rad",
             "held-out torque RMSD per candidate: " + ", ".join(
                 f"{name} {c['held_out_rmsd']:.4f}" for name, c in result.candidates.items())]
    worst = max(result.localisation_before["by_speed_rad_s"], key=lambda b: b["rmsd"])
    lines.append(f"largest disagreement before: |qd| in [{worst['from']}, {worst['to']}) "
                 f"rad/s, {worst['rmsd']:.3f} N.m")
    return "\n".join(lines)


def save_plots(result: GapResult, directory: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory.mkdir(parents=True, exist_ok=True)
    r = result.residuals
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, key, label in ((axes[0], "speed", "joint velocity (rad/s)"),
                           (axes[1], "position", "joint position (rad)")):
        ax.plot(r[key], r["before"], ".", markersize=1.5, alpha=0.5, label="before")
        ax.plot(r[key], r["after"], ".", markersize=1.5, alpha=0.5,
                label=f"after ({result.effect})")
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("motor torque residual (N.m)")
    axes[0].legend(markerscale=6)
    fig.suptitle(f"torque residual: RMSD {result.rmsd_before:.3f} -> {result.rmsd_after:.3f} "
                 "N.m")
    fig.tight_layout()
    paths = [directory / "residuals.png"]
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    # the windows where the old model was most wrong: that is where the gap shows
    worst = sorted(range(len(result.traces_before)), reverse=True,
                   key=lambda i: float(np.sum((result.traces_before[i][2]
                                               - result.traces_before[i][1]) ** 2)))[:6]
    fig, axes = plt.subplots(2, 3, figsize=(12, 6))
    for ax, index in zip(axes.flat, sorted(worst), strict=False):
        t, measured, before = result.traces_before[index]
        after = result.traces_after[index][2]
        ax.plot(t, measured, color="black", linewidth=1.4, label="measured")
        ax.plot(t, before, color="C3", linewidth=1.0, label="simulated, before")
        ax.plot(t, after, color="C2", linewidth=1.0, linestyle="--", label="simulated, after")
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("position (rad)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"simulations restarted every {result.horizon} s from the measured state "
                 f"(the 6 worst windows): RMSD {result.sim_rmsd_before:.4f} -> "
                 f"{result.sim_rmsd_after:.4f} rad")
    fig.tight_layout()
    paths.append(directory / "simulation.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(7, 4))
    for key, label in (("where_before", "before"), ("where_after", "after")):
        bins = (result.localisation_before if key == "where_before"
                else result.localisation_after)["by_speed_rad_s"]
        centres = [np.sqrt(max(b["from"], 1e-3) * b["to"]) for b in bins]
        ax.semilogx(centres, [b["rmsd"] for b in bins], "o-", label=label)
    ax.set(xlabel="|joint velocity| (rad/s)", ylabel="torque residual RMS (N.m)",
           title="where the model disagrees: by speed")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    paths.append(directory / "by_speed.png")
    fig.savefig(paths[-1], dpi=100)
    plt.close(fig)
    return paths


if __name__ == "__main__":
    sys.exit(main())
