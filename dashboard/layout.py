"""The Foxglove layout, built with foxglove-sdk's `foxglove.layouts` (the current layout format:
panel titles as the viewers show them, typed panel configs) instead of hand-written JSON that
drifts from the telemetry. The shipped `dashboard/elbow_layout.json` (live bridge and Zenoh
recordings) and `dashboard/elbow_experiment_layout.json` (experiment recordings: no MPC, no
services) are this module's output; a test regenerates them and compares.

    python3 -m dashboard.layout                          # rewrite both shipped layouts
    python3 -m dashboard.layout --prefix actuators/elbow --prefix actuators/wrist -o arm.json
    python3 -m dashboard.layout --robot robots/talos_arm.toml -o talos_arm.json

Topics are the Zenoh key expressions themselves (`actuators/elbow/state`): the bridge
forwards each key under its own name and both kinds of recording name their channels the same
way, so one layout serves the live bridge, experiment recordings and Zenoh recordings.
Services are named the same way (`actuators/elbow/reference`, `actuators/elbow/weights`).
"""

import argparse
import json
import sys
from dataclasses import dataclass
from importlib.resources import files
from pathlib import Path

import foxglove.layouts as fl

from protocol import telemetry

SHIPPED = "elbow_layout.json"
SHIPPED_EXPERIMENT = "elbow_experiment_layout.json"
LIMIT_COLOR = "#d62728"  # red: every limit line, dotted
WINDOW_S = 20.0  # seconds of history the live plots follow

# example requests shown in the service panels (what `dashboard set` would send)
REFERENCE_EXAMPLE = {"kind": "setpoint", "position": -1.0}
WEIGHTS_EXAMPLE = {"position": 300}


@dataclass(frozen=True)
class JointPaths:
    """Where one joint's values live, as Foxglove message paths. A joint driven by its own
    actuatord has its own State and Command topics (`own_topics`); a many-joint message with
    per-joint arrays adds a constructor giving `topic.position[i]` and leaves the panels as
    they are."""

    name: str
    position: str
    reference: str
    position_min: str
    position_max: str
    motor_current: str
    commanded_current: str
    planned_current: str
    current_limit: str
    joint_torque: str
    drive_state: str
    fallback: str
    saturated: str

    @classmethod
    def own_topics(cls, prefix: str) -> "JointPaths":
        state = telemetry.key_expr(prefix, "state")
        command = telemetry.key_expr(prefix, "command")
        return cls(name=prefix.rstrip("/").rsplit("/", 1)[-1],
                   position=f"{state}.position", reference=f"{command}.reference_position",
                   position_min=f"{command}.position_min",
                   position_max=f"{command}.position_max",
                   motor_current=f"{state}.motor_current", commanded_current=f"{command}.current",
                   planned_current=f"{command}.planned_current",
                   current_limit=f"{command}.current_limit",
                   joint_torque=f"{state}.joint_torque", drive_state=f"{state}.drive_state",
                   fallback=f"{command}.fallback", saturated=f"{command}.saturated")


def _series(path: str, label: str, color: str, style: str = "solid",
            width: float = 1.5) -> fl.PlotSeries:
    return fl.PlotSeries(value=path, label=label, color=color, line_style=style,
                         line_size=width, enabled=True, timestamp_method="receiveTime")


def _plot(title: str, unit: str, series: list[fl.PlotSeries]) -> fl.PlotPanel:
    return fl.PlotPanel(title=title, config=fl.PlotConfig(
        paths=series, show_legend=True, legend_display="top", x_axis_val="timestamp",
        time_window_mode="sliding", following_view_width=WINDOW_S, y_axis_label=unit,
        show_plot_values_in_legend=True))


def _limits(low: str, high: str, what: str) -> list[fl.PlotSeries]:
    return [_series(low, f"{what} lower limit", LIMIT_COLOR, "dotted", 1.0),
            _series(high, f"{what} upper limit", LIMIT_COLOR, "dotted", 1.0)]


def _service_panel(title: str, service: str, example: dict) -> fl.ServiceCallPanel:
    return fl.ServiceCallPanel(title=title, config=fl.ServiceCallConfig(
        service_name=service, request_payload=json.dumps(example), layout="vertical",
        button_text="send", editing_mode=True, timeout_seconds=5))


def joint_view(prefix: str, joint: JointPaths, experiment: bool = False) -> fl.SplitContainer:
    """Every panel for one actuatord: tracking, current against its limits (measured above
    commanded above the solver's plan, each its own style), torque, drive state, solver and
    loop timing, faults, and the reference and weights services. `experiment`: the panels an
    experiment recording feeds (`recorder --exciting-trajectory/--sinusoid`): its tracking law
    has no MPC (no solver topic, no planned current) and no services, so timing comes from
    loop_stats alone (the law's decide time and the loop's jitter)."""
    position = _plot("position vs reference and limits", "rad", [
        _series(joint.position, "measured position", "#1f77b4", width=2),
        _series(joint.reference, "reference", "#7f7f7f", "dashed"),
        *_limits(joint.position_min, joint.position_max, "position")])
    current = _plot("motor current vs limit", "A", [
        _series(joint.motor_current, "measured current", "#ff7f0e", width=2),
        _series(joint.commanded_current, "commanded current", "#2ca02c"),
        *([] if experiment else [
            _series(joint.planned_current, "solver current", "#9467bd", "dashed")]),
        *_limits(f"{joint.current_limit}.@negative", joint.current_limit, "current")])
    torque = _plot("joint torque (torque sensor)", "N.m", [
        _series(joint.joint_torque, "joint torque", "#8c564b")])
    solver, stats = telemetry.key_expr(prefix, "solver"), telemetry.key_expr(prefix, "loop_stats")
    timing = _plot("MPC tick and loop jitter", "us", [
        _series(f"{solver}.solve_time_us", "MPC tick", "#17becf"),
        _series(f"{stats}.solve_p99_us", "MPC tick p99 (1 s)", "#1f77b4", "dashed"),
        _series(f"{stats}.period_jitter_p99_us", "period jitter p99 (1 s)", "#e377c2")])
    if experiment:
        timing = _plot("tracking law and loop jitter", "us", [
            _series(f"{stats}.solve_p99_us", "tracking law p99 (1 s)", "#1f77b4", "dashed"),
            _series(f"{stats}.period_jitter_p99_us", "period jitter p99 (1 s)", "#e377c2")])
    states = fl.StateTransitionsPanel(title="drive state and safety net",
                                      config=fl.StateTransitionsConfig(paths=[
        fl.StateTransitionsSeries(value=joint.drive_state, label="CiA 402 state"),
        fl.StateTransitionsSeries(value=joint.fallback, label="safety fallback"),
        fl.StateTransitionsSeries(value=joint.saturated, label="current saturated")],
        show_legend=True, time_window_mode="sliding", x_axis_range=WINDOW_S))
    faults = fl.RawMessagesPanel(title="last fault", config=fl.RawMessagesConfig(
        topic_path=telemetry.key_expr(prefix, "fault"), expansion="all"))
    services = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(content=_service_panel(
            "set reference", telemetry.key_expr(prefix, telemetry.REFERENCE),
            REFERENCE_EXAMPLE)),
        fl.SplitItem(content=_service_panel(
            "set weights", telemetry.key_expr(prefix, telemetry.WEIGHTS), WEIGHTS_EXAMPLE))])

    def row(*panels, proportion: float = 1) -> fl.SplitItem:
        return fl.SplitItem(proportion=proportion, content=fl.SplitContainer(
            direction="row", items=[fl.SplitItem(content=p) for p in panels]))

    return fl.SplitContainer(direction="column", items=[
        row(position, current, proportion=3), row(torque, timing, states, proportion=2),
        row(faults, *([] if experiment else [services]), proportion=2)])


def build_layout(prefixes: list[str] | None = None, experiment: bool = False) -> fl.Layout:
    """The layout for the actuatords under `prefixes` (default: the elbow); several get a tab
    each. `experiment`: for experiment recordings (see joint_view)."""
    prefixes = prefixes or [telemetry.DEFAULT_PREFIX]
    joints = {prefix: JointPaths.own_topics(prefix) for prefix in prefixes}
    views = [fl.TabItem(title=joint.name, content=joint_view(prefix, joint, experiment))
             for prefix, joint in joints.items()]
    if len(views) == 1:
        return fl.Layout(content=views[0].content)
    return fl.Layout(content=fl.TabContainer(tabs=views))


# one colour per joint, repeating past ten joints (matplotlib's tab10, as the other plots)
JOINT_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
                "#7f7f7f", "#bcbd22", "#17becf")


def robot_layout(prefix: str, names: list[str]) -> fl.Layout:
    """The layout for `actuatord --robot`: its one JointStates message a cycle under
    `{prefix}/joints` holds every joint as arrays in the robot file's order, so joint i is
    `joints.position[i]`. A tab with every joint together (positions, currents, drive states)
    and a tab per joint (position against its reference; measured, commanded and planned
    current). The message carries no limits: the limit lines of a one-joint view are left out."""
    joints = telemetry.key_expr(prefix, "joints")

    def path(field: str, i: int) -> str:
        return f"{joints}.{field}[{i}]"

    def color(i: int) -> str:
        return JOINT_COLORS[i % len(JOINT_COLORS)]

    positions = _plot("every joint's position", "rad", [
        _series(path("position", i), name, color(i)) for i, name in enumerate(names)])
    currents = _plot("every joint's measured current", "A", [
        _series(path("motor_current", i), name, color(i)) for i, name in enumerate(names)])
    states = fl.StateTransitionsPanel(title="drive states", config=fl.StateTransitionsConfig(
        paths=[fl.StateTransitionsSeries(value=path("drive_state", i), label=name)
               for i, name in enumerate(names)],
        show_legend=True, time_window_mode="sliding", x_axis_range=WINDOW_S))
    stats = telemetry.key_expr(prefix, "loop_stats")
    timing = _plot("batched MPC tick and loop jitter", "us", [
        _series(f"{joints}.solve_time_us", "MPC tick (all joints)", "#17becf"),
        _series(f"{stats}.period_jitter_p99_us", "period jitter p99 (1 s)", "#e377c2")])
    faults = fl.RawMessagesPanel(title="last fault", config=fl.RawMessagesConfig(
        topic_path=telemetry.key_expr(prefix, "fault"), expansion="all"))
    overview = fl.SplitContainer(direction="column", items=[
        fl.SplitItem(proportion=3, content=fl.SplitContainer(direction="row", items=[
            fl.SplitItem(content=positions), fl.SplitItem(content=currents)])),
        fl.SplitItem(proportion=2, content=fl.SplitContainer(direction="row", items=[
            fl.SplitItem(content=states), fl.SplitItem(content=timing),
            fl.SplitItem(content=faults)]))])
    tabs = [fl.TabItem(title="all joints", content=overview)]
    for i, name in enumerate(names):
        tabs.append(fl.TabItem(title=name, content=fl.SplitContainer(direction="row", items=[
            fl.SplitItem(content=_plot("position vs reference", "rad", [
                _series(path("position", i), "measured position", "#1f77b4", width=2),
                _series(path("reference_position", i), "reference", "#7f7f7f", "dashed")])),
            fl.SplitItem(content=_plot("motor current", "A", [
                _series(path("motor_current", i), "measured current", "#ff7f0e", width=2),
                _series(path("current", i), "commanded current", "#2ca02c"),
                _series(path("planned_current", i), "solver current", "#9467bd",
                        "dashed")]))])))
    return fl.Layout(content=fl.TabContainer(tabs=tabs))


def layout_json(layout: fl.Layout) -> str:
    """The layout as the file holds it: the SDK's JSON, indented so reviews can diff it."""
    return json.dumps(json.loads(layout.to_json()), indent=2) + "\n"


def shipped_path(experiment: bool = False) -> Path:
    return Path(str(files("dashboard") / (SHIPPED_EXPERIMENT if experiment else SHIPPED)))


def _robot_names(path: str) -> tuple[str, list[str]] | None:
    """The robot's name and its joints' names, in order, from a robot file (read as TOML
    here: the dashboard layer imports only `protocol`, not `robot.description`, which checks
    robot files whole)."""
    import tomllib

    try:
        data = tomllib.loads(Path(path).read_text())
        return data["robot"]["name"], [joint["name"] for joint in data["joints"]]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python3 -m dashboard.layout",
                                     description="write the Foxglove layout")
    parser.add_argument("--prefix", action="append", default=[],
                        help=f"an actuatord's key prefix, repeatable (default: "
                             f"{telemetry.DEFAULT_PREFIX})")
    parser.add_argument("--robot", metavar="FILE",
                        help="the layout for actuatord --robot FILE (its prefix robots/NAME "
                             "unless --prefix gives one)")
    parser.add_argument("--experiment", action="store_true",
                        help="the layout for experiment recordings (no MPC, no services)")
    parser.add_argument("-o", "--output", type=Path, default=None,
                        help=f"default: rewrite the shipped dashboard/{SHIPPED} and "
                             f"dashboard/{SHIPPED_EXPERIMENT}")
    args = parser.parse_args(argv)
    if (args.prefix or args.robot or args.experiment) and args.output is None:
        parser.error("--prefix/--robot/--experiment need -o FILE: the shipped layouts are "
                     "the elbow's")
    if args.output is None:
        for experiment in (False, True):
            shipped_path(experiment).write_text(layout_json(build_layout(None, experiment)))
            print(f"wrote {shipped_path(experiment)}")
        return 0
    output = args.output
    if args.robot:
        robot = _robot_names(args.robot)
        if robot is None:
            parser.error(f"--robot {args.robot}: not a robot file ([robot] name and "
                         "[[joints]] names)")
        name, names = robot
        layout = robot_layout(args.prefix[0] if args.prefix else f"robots/{name}", names)
    else:
        layout = build_layout(args.prefix, args.experiment)
    output.write_text(layout_json(layout))
    print(f"wrote {output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
