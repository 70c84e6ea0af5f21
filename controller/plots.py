"""Figures like the paper's Fig. 5-8 from a run's history (matplotlib, written as PNG)."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from model.parameters import Limits  # noqa: E402


def save_figures(history: dict, limits: Limits, directory: Path, title: str) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    t = history["t"]
    paths = []

    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(t, history["reference"], "--", color="gray", label="reference")
    ax.plot(t, history["position"], color="C0", label="joint position")
    for bound in (limits.position_min, limits.position_max):
        ax.axhline(bound, color="C3", linewidth=0.8)
    ax.set(xlabel="time (s)", ylabel="position (rad)", title=f"{title}: state trajectory")
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    paths.append(directory / "position.png")
    fig.tight_layout()
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 4))
    ax.plot(t, history["planned_current"], color="C2", alpha=0.6, label="solver current")
    ax.plot(t, history["current"], color="C1", label="commanded current")
    for bound in (-limits.current_max, limits.current_max):
        ax.axhline(bound, color="C3", linewidth=0.8)
    ax.set(xlabel="time (s)", ylabel="motor current (A)", title=f"{title}: control trajectory")
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    paths.append(directory / "current.png")
    fig.tight_layout()
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths
