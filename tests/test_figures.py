"""actuatord --plot figures: every series visible where series coincide, the measured current
shown, the limits named and labelled with their value."""

import matplotlib.pyplot as plt
import numpy as np
import pytest

from controller.plots import current_figure, position_figure
from model.parameters import Limits

LIMITS = Limits(position_min=-2.35, position_max=0.0, velocity_max=5.0, current_max=6.0)


@pytest.fixture
def history() -> dict:
    """The solver's current equal to the commanded one except where the net clips it: the
    case that hid one series under the other."""
    t = np.arange(0, 2, 1e-3)
    planned = 7.0 * np.sin(2 * np.pi * t)
    commanded = np.clip(planned, -6.0, 6.0)
    return {"t": t, "position": -1 + 0.5 * np.sin(t), "reference": -1 + 0.5 * np.sin(t + 0.1),
            "velocity": 0.5 * np.cos(t), "current": commanded, "planned_current": planned,
            "motor_current": commanded + np.random.default_rng(0).normal(0, 0.05, t.size),
            "joint_torque": 3 * commanded}


def drawn(figure) -> dict[str, object]:
    """label -> line, for every labelled line of the figure's one axes."""
    (ax,) = figure.axes
    return {line.get_label(): line for line in ax.get_lines()
            if not line.get_label().startswith("_")}


def test_current_figure_shows_every_series_and_names_the_limits(history):
    figure = current_figure(history, LIMITS, "test")
    try:
        lines = drawn(figure)
        measured = lines["motor current (measured)"]
        commanded = lines["commanded current (sent to the drive)"]
        solver = lines["solver current (before the safety net)"]
        np.testing.assert_array_equal(measured.get_ydata(), history["motor_current"])
        # where the three coincide: a translucent band, a thin line in it, dashes on top
        assert solver.get_zorder() > measured.get_zorder() > commanded.get_zorder()
        assert solver.get_linestyle() != commanded.get_linestyle()
        assert solver.get_linewidth() < commanded.get_linewidth()
        assert measured.get_linewidth() < commanded.get_linewidth()
        assert commanded.get_alpha() < 1
        styles = [(line.get_color(), line.get_linestyle()) for line in lines.values()]
        assert len(set(styles)) == len(styles)
        assert "current limits [-6, +6] A" in lines
        (ax,) = figure.axes
        assert {text.get_text() for text in ax.texts} == {"-6 A", "+6 A"}
        legend = {text.get_text() for text in ax.get_legend().get_texts()}
        assert legend == set(lines)
    finally:
        plt.close(figure)


def test_position_figure_names_reference_measurement_and_limits(history):
    figure = position_figure(history, LIMITS, "test")
    try:
        lines = drawn(figure)
        assert set(lines) == {"reference", "joint position (measured)",
                              "position limits [-2.35, +0] rad"}
        assert lines["joint position (measured)"].get_zorder() > lines["reference"].get_zorder()
        (ax,) = figure.axes
        assert {text.get_text() for text in ax.texts} == {"-2.35 rad", "+0 rad"}
    finally:
        plt.close(figure)
