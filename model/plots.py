"""Figures of the identification fit and of model-gap's before/after (matplotlib, PNG).

matplotlib is imported when a figure is drawn, so the rest of `model` never pays for it.
"""

from pathlib import Path

import numpy as np

from model.gap.report import GapResult
from model.identify import Identified


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def identification_figures(result: Identified, directory: Path) -> list[Path]:
    """One figure per experiment: for the motor and the joint torque, the measurement and the
    model in panels of their own (same scale), and their difference below."""
    plt = _pyplot()
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for index, (name, fit) in enumerate(result.fits.items()):
        fig, axes = plt.subplots(3, 2, figsize=(12, 7.5), sharex=True,
                                 gridspec_kw={"height_ratios": [2, 2, 1.2]})
        for column, side in enumerate(("motor", "joint")):
            measured, predicted = fit[f"measured_{side}"], fit[f"predicted_{side}"]
            low = min(measured.min(), predicted.min())
            high = max(measured.max(), predicted.max())
            for row, (values, label, color) in enumerate(((measured, "measured", "black"),
                                                          (predicted, "model", "C0"))):
                ax = axes[row, column]
                ax.plot(fit["t"], values, ".", markersize=1.5, color=color)
                ax.set_ylim(low - 0.05 * (high - low), high + 0.05 * (high - low))
                ax.set_title(f"{side} torque: {label}", fontsize=10)
                ax.grid(alpha=0.3)
            residual = predicted - measured
            ax = axes[2, column]
            ax.plot(fit["t"], residual, ".", markersize=1.5, color="C3")
            ax.axhline(0.0, color="gray", linewidth=0.8)
            ax.set_title(f"model - measured: RMSD {np.sqrt(np.mean(residual**2)):.3f} N.m",
                         fontsize=10)
            ax.set_xlabel("time (s)")
            ax.grid(alpha=0.3)
        for row, label in enumerate(("torque (N.m)", "torque (N.m)", "residual (N.m)")):
            axes[row, 0].set_ylabel(label)
        fig.suptitle(f"identification fit: {Path(name).name} (samples moving faster than the "
                     "identification's minimum speed)")
        fig.tight_layout()
        paths.append(directory / f"fit_{index}_{Path(name).stem}.png")
        fig.savefig(paths[-1], dpi=100)
        plt.close(fig)
    return paths


def gap_figures(result: GapResult, directory: Path) -> list[Path]:
    """The torque residual before and after (by speed and position), the restarted
    simulations where the old model was most wrong, and the residual by speed."""
    plt = _pyplot()
    directory.mkdir(parents=True, exist_ok=True)
    after_label = f"after ({result.effect})"
    r = result.residuals
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, key, label in ((axes[0], "speed", "joint velocity (rad/s)"),
                           (axes[1], "position", "joint position (rad)")):
        ax.plot(r[key], r["before"], ".", markersize=1.5, alpha=0.5, label="before")
        ax.plot(r[key], r["after"], ".", markersize=1.5, alpha=0.5, label=after_label)
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
        ax.plot(t, after, color="C2", linewidth=1.0, linestyle="--",
                label=f"simulated, {after_label}")
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
    for bins, label in ((result.localisation_before["by_speed_rad_s"], "before"),
                        (result.localisation_after["by_speed_rad_s"], after_label)):
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
