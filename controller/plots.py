"""Figures like the paper's Fig. 5-8 from a run's history (matplotlib, written as PNG)."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from model.parameters import Limits  # noqa: E402


def save_figures(history: dict, limits: Limits, directory: Path, title: str) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    return [
        _figure(history, directory / "position.png",
                [("reference", "--", "gray", 1.0, "reference"),
                 ("position", "-", "C0", 1.0, "joint position")],
                (limits.position_min, limits.position_max), "position (rad)",
                f"{title}: state trajectory"),
        _figure(history, directory / "current.png",
                [("planned_current", "-", "C2", 0.6, "solver current"),
                 ("current", "-", "C1", 1.0, "commanded current")],
                (-limits.current_max, limits.current_max), "motor current (A)",
                f"{title}: control trajectory"),
    ]


def _figure(history: dict, path: Path, series: list[tuple], bounds: tuple[float, float],
            ylabel: str, title: str) -> Path:
    """One time plot: the series (key, line style, colour, alpha, label) and the two limits."""
    fig, ax = plt.subplots(figsize=(8, 4))
    for key, style, color, alpha, label in series:
        ax.plot(history["t"], history[key], style, color=color, alpha=alpha, label=label)
    for bound in bounds:
        ax.axhline(bound, color="C3", linewidth=0.8)
    ax.set(xlabel="time (s)", ylabel=ylabel, title=title)
    ax.legend(loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
