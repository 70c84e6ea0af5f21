"""Figures like the paper's Fig. 5-8 from a run's history (matplotlib, written as PNG).

Every series must stay visible where series coincide: the drive follows the command closely
and the solver's current equals the commanded one except when the safety net clips or
replaces it. So the commanded current is a wide translucent band underneath, the measured
current a thin line inside it, and the solver's current dashes on top. Limits are dotted red
lines, named in the legend and labelled with their value."""

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from model.parameters import Limits  # noqa: E402

LIMIT_COLOR = "#d62728"


@dataclass(frozen=True)
class Series:
    """One history key as drawn: later entries are drawn on top (zorder follows the order)."""

    key: str
    label: str
    color: str
    style: str = "-"
    width: float = 1.5
    alpha: float = 1.0


POSITION_SERIES = (
    Series("reference", "reference", "#7f7f7f", "--", 1.2),
    Series("position", "joint position (measured)", "#1f77b4", "-", 1.6),
)
CURRENT_SERIES = (
    Series("current", "commanded current (sent to the drive)", "#1f77b4", "-", 4.0, 0.35),
    Series("motor_current", "motor current (measured)", "#ff7f0e", "-", 1.0),
    Series("planned_current", "solver current (before the safety net)", "#2ca02c",
           (0, (4, 3)), 1.3),
)


def position_figure(history: dict, limits: Limits, title: str) -> Figure:
    return _figure(history, POSITION_SERIES, "position", "rad",
                   (limits.position_min, limits.position_max), f"{title}: state trajectory")


def current_figure(history: dict, limits: Limits, title: str) -> Figure:
    return _figure(history, CURRENT_SERIES, "current", "A",
                   (-limits.current_max, limits.current_max), f"{title}: control trajectory")


def save_figures(history: dict, limits: Limits, directory: Path, title: str) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, figure in (("position", position_figure(history, limits, title)),
                         ("current", current_figure(history, limits, title))):
        path = directory / f"{name}.png"
        figure.savefig(path, dpi=110)
        plt.close(figure)
        paths.append(path)
    return paths


def _figure(history: dict, series: tuple[Series, ...], quantity: str, unit: str,
            bounds: tuple[float, float], title: str) -> Figure:
    """One time plot: the series in order, and the two limits as labelled dotted lines."""
    fig, ax = plt.subplots(figsize=(8, 4))
    for z, s in enumerate(series, start=2):
        ax.plot(history["t"], history[s.key], linestyle=s.style, color=s.color,
                linewidth=s.width, alpha=s.alpha, label=s.label, zorder=z)
    low, high = bounds
    for bound, label in ((low, f"{quantity} limits [{low:+g}, {high:+g}] {unit}"),
                         (high, None)):
        ax.axhline(bound, color=LIMIT_COLOR, linestyle=":", linewidth=1.2, label=label,
                   zorder=1)
        ax.annotate(f"{bound:+g} {unit}", xy=(1.0, bound), xycoords=("axes fraction", "data"),
                    xytext=(-4, -11 if bound == high else 3), textcoords="offset points",
                    ha="right", color=LIMIT_COLOR, fontsize=8)
    ax.set(xlabel="time (s)", ylabel=f"{quantity} ({unit})", title=title)
    ax.legend(loc="best", fontsize=8, framealpha=0.85)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig
