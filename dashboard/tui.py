"""`dashboard tui`: the actuator at a glance in a terminal on the robot. A table with a row per
joint, position and current against their limits as bars, solver and loop statistics, faults
highlighted, a short scrolling plot of position and current, and a status line that says when
the data is stale or actuatord has vanished.

actuatord publishes at 1 kHz; a screen shows 20 frames a second. So Zenoh keeps only the
newest message per topic (and every fault) and the screen takes what is there at its own
rate: the dashboard's clock stays on the publisher's however fast it publishes, no Python runs
per message, and quitting leaves no callback writing into a stopped app."""

import time
from collections import deque
from dataclasses import dataclass

import zenoh
from rich.text import Text
from textual.app import App, ComposeResult
from textual.containers import Horizontal, Vertical
from textual.widgets import DataTable, Footer, Header, Log, Sparkline, Static

from dashboard.liveliness import watch_publisher
from protocol import telemetry

# Every widget redrawn costs Textual a few ms of CPU, so each part is redrawn only as often as
# eyes need it: the status line (clock, stale, vanished) every frame, the plots every
# PLOT_EVERY frames, the numbers every READOUT_EVERY (faster is unreadable anyway).
REFRESH_HZ = 20  # frames a second
PLOT_EVERY = 2  # 10 Hz
READOUT_EVERY = 4  # 5 Hz
STALE_S = 0.5  # no state for this long (500 cycles at 1 kHz) and the values are marked stale
HISTORY = 200  # points in the scrolling plots: 10 s at REFRESH_HZ
BAR_WIDTH = 40
# not the large plan; `joints` is actuatord --robot's one message with every joint
LATEST_ONLY = ("state", "command", "solver", "loop_stats", "joints")
CLASSES = telemetry.TOPICS
FAULTS_KEPT = 1000  # faults waiting for the next frame; a fault storm drops the oldest


class Feed:
    """actuatord's topics under a prefix as a screen wants them. Zenoh keeps only the newest
    message of each topic (a ring channel of one, filled in Zenoh's own threads: no Python
    runs per message), every fault up to FAULTS_KEPT, and the liveliness of actuatord
    (`alive`: None until known)."""

    def __init__(self, session: zenoh.Session, prefix: str):
        self._latest = {topic: session.declare_subscriber(
            telemetry.key_expr(prefix, topic), zenoh.handlers.RingChannel(1))
            for topic in LATEST_ONLY}
        self._faults = session.declare_subscriber(telemetry.key_expr(prefix, "fault"),
                                                  zenoh.handlers.RingChannel(FAULTS_KEPT))
        self.alive: bool | None = None
        self._liveliness = watch_publisher(session, prefix, self._set_alive)

    def _set_alive(self, alive: bool) -> None:
        self.alive = alive

    def take(self) -> tuple[dict[str, bytes], list[bytes]]:
        """What arrived since the last call: the newest message per topic, the faults."""
        latest = {}
        for topic, subscriber in self._latest.items():
            sample = subscriber.try_recv()
            if sample is not None:
                latest[topic] = sample.payload.to_bytes()
        faults = []
        while (sample := self._faults.try_recv()) is not None:
            faults.append(sample.payload.to_bytes())
        return latest, faults

    def close(self) -> None:
        for subscriber in [*self._latest.values(), self._faults, self._liveliness]:
            subscriber.undeclare()


@dataclass(frozen=True)
class JointRow:
    """One joint as the table shows it: from one actuatord's State and Command, or one per
    joint from a robot's JointStates arrays."""

    name: str
    position: float
    reference: float
    velocity: float
    motor_current: float
    commanded_current: float
    joint_torque: float
    drive_state: str


JOINT_COLUMNS = ("joint", "position rad", "reference rad", "velocity rad/s", "current A",
                 "commanded A", "torque N.m", "drive state")


def joint_row(name: str, state, command) -> JointRow:
    nan = float("nan")
    return JointRow(name, state.position, command.reference_position if command else nan,
                    state.velocity, state.motor_current, command.current if command else nan,
                    state.joint_torque, state.drive_state)


def joint_rows_of(states) -> list[JointRow]:
    """A robot's JointStates as one row per joint, in the robot file's order."""
    return [JointRow(*values) for values in zip(
        states.name, states.position, states.reference_position, states.velocity,
        states.motor_current, states.current, states.effort, states.drive_state, strict=True)]


def row_cells(row: JointRow) -> tuple[str, ...]:
    return (row.name, f"{row.position:+.4f}", f"{row.reference:+.3f}", f"{row.velocity:+.4f}",
            f"{row.motor_current:+.3f}", f"{row.commanded_current:+.3f}",
            f"{row.joint_torque:+.3f}", row.drive_state)


def limit_bar(value: float, low: float, high: float, width: int = BAR_WIDTH) -> Text:
    """A bar from low to high with the value marked; red within 5 % of either end."""
    span = high - low
    fraction = 0.0 if span <= 0 else min(max((value - low) / span, 0.0), 1.0)
    filled = int(round(fraction * width))
    near = fraction < 0.05 or fraction > 0.95
    bar = Text(f"{low:+7.2f} ")
    bar.append("█" * filled, style="bold red" if near else "green")
    bar.append("░" * (width - filled), style="grey50")
    bar.append(f" {high:+7.2f}")
    return bar


def status_line(alive: bool | None, state_age: float | None, t: float | None,
                prefix: str) -> Text:
    """What the viewer must know before reading any value: is it live, stale or orphaned."""
    clock = f"t {t:10.3f} s" if t is not None else "no state yet"
    if alive is False:
        return Text(f" actuatord under {prefix} VANISHED (liveliness token gone): values are "
                    f"its last · {clock} ", style="bold white on red")
    if state_age is None:
        return Text(f" waiting for {prefix}/state ... ", style="bold black on yellow")
    if state_age > STALE_S:
        return Text(f" STALE: no state for {state_age:.1f} s · {clock} ",
                    style="bold black on yellow")
    return Text(f" live · {clock} ", style="bold black on green")


class ElbowDashboard(App):
    CSS = """
    #status { height: 1; }
    #joints { height: auto; max-height: 12; border: round $accent; }
    #bars { height: 5; border: round $accent; padding: 0 1; }
    #stats { height: 5; border: round $accent; padding: 0 1; }
    #plots { height: 7; }
    .plot { width: 1fr; height: 7; border: round $accent; }
    #faults { height: 1fr; border: round red; }
    """
    BINDINGS = [("q", "quit", "quit")]

    def __init__(self, feed: Feed, prefix: str = telemetry.DEFAULT_PREFIX):
        super().__init__()
        self.prefix = prefix
        self.feed = feed
        self.title = f"actuator-link: {prefix}"
        self.joint_name = prefix.rstrip("/").rsplit("/", 1)[-1]
        self.positions: deque[float] = deque(maxlen=HISTORY)
        self.currents: deque[float] = deque(maxlen=HISTORY)
        self.state = None
        self.joints = None  # JointStates, when the publisher is actuatord --robot
        self.command = None
        self.solver = None
        self.loop_stats = None
        self.state_received: float | None = None  # time.monotonic() of the latest state
        self.faults = 0
        self._frame = 0
        self._new_state = False  # a state came since the plots were last drawn
        self._message_classes = {topic: telemetry.message_class(CLASSES[topic])
                                 for topic in (*LATEST_ONLY, "fault")}

    @property
    def clock(self) -> float | None:
        """Drive time of the state on screen: how far the dashboard has got."""
        latest = self.state if self.state is not None else self.joints
        return latest.t if latest is not None else None

    def compose(self) -> ComposeResult:
        yield Header()
        with Vertical():
            yield Static(id="status")
            yield DataTable(id="joints", show_cursor=False, zebra_stripes=True)
            yield Static(id="bars")
            yield Static(id="stats")
            with Horizontal(id="plots"):
                yield Sparkline([], id="position_plot", classes="plot")
                yield Sparkline([], id="current_plot", classes="plot")
            yield Log(id="faults")
        yield Footer()

    def on_mount(self) -> None:
        self.query_one("#joints", DataTable).border_title = "joints"
        self.query_one("#joints", DataTable).add_columns(*JOINT_COLUMNS)
        self.query_one("#bars", Static).border_title = "limits"
        self.query_one("#stats", Static).border_title = "solver and loop"
        self.query_one("#position_plot", Sparkline).border_title = "position"
        self.query_one("#current_plot", Sparkline).border_title = "current"
        self.query_one("#faults", Log).border_title = "faults"
        self.refresh_view()
        # the frame timer belongs to the screen it draws, so it stops before the screen's
        # widgets go away on quit (an app timer fired once more into a torn-down screen)
        self.screen.set_interval(1 / REFRESH_HZ, self.poll)

    def poll(self) -> None:
        """One frame: take what arrived since the last, show it."""
        latest, faults = self.feed.take()
        for topic, data in latest.items():
            message = self._message_classes[topic]()
            message.ParseFromString(data)
            self.ingest(topic, message)
        for data in faults:
            message = self._message_classes["fault"]()
            message.ParseFromString(data)
            self.ingest("fault", message)
        self._new_state = self._new_state or "state" in latest or "joints" in latest
        self._draw_status()
        if self._frame % PLOT_EVERY == 0 and self._new_state:
            self._draw_plots()
            self._new_state = False
        if self._frame % READOUT_EVERY == 0:
            self._draw_readouts()
        self._frame += 1

    def ingest(self, topic: str, message) -> None:
        """Take one decoded telemetry message (on the app's thread); shown at the next
        frame."""
        if topic == "state":
            self.state = message
            self.state_received = time.monotonic()  # within a frame of its arrival
            self.positions.append(message.position)
            self.currents.append(message.motor_current)
        elif topic == "joints":
            # the plots follow the robot file's first joint; the table shows them all
            self.joints = message
            self.state_received = time.monotonic()
            if message.position:
                self.positions.append(message.position[0])
                self.currents.append(message.motor_current[0])
        elif topic == "command":
            self.command = message
        elif topic == "solver":
            self.solver = message
        elif topic == "loop_stats":
            self.loop_stats = message
        elif topic == "fault":
            self.faults += 1
            self.query_one("#faults", Log).write_line(
                f"t={message.t:9.3f} s [{message.source}] {message.cause} -> {message.action}")

    def joint_rows(self) -> list[JointRow]:
        if self.joints is not None:
            return joint_rows_of(self.joints)
        return [joint_row(self.joint_name, self.state, self.command)] if self.state else []

    def refresh_view(self) -> None:
        self._draw_status()
        self._draw_plots()
        self._draw_readouts()

    def _draw_status(self) -> None:
        """Live, stale or vanished, and the clock."""
        age = None if self.state_received is None else time.monotonic() - self.state_received
        self.query_one("#status", Static).update(
            status_line(self.feed.alive, age, self.clock, self.prefix), layout=False)

    def _draw_plots(self) -> None:
        self.query_one("#position_plot", Sparkline).data = list(self.positions)
        self.query_one("#current_plot", Sparkline).data = list(self.currents)

    def _draw_readouts(self) -> None:
        s, c = self.state, self.command
        self._show_joints(self.joint_rows())
        if s is not None and c is not None:
            bars = Text("position ")
            bars.append(limit_bar(s.position, c.position_min, c.position_max))
            bars.append("\ncurrent  ")
            bars.append(limit_bar(s.motor_current, -c.current_limit, c.current_limit))
            if c.fallback:
                bars.append("\nSAFETY FALLBACK ACTIVE", style="bold white on red")
            elif c.saturated:
                bars.append("\ncommand saturated at the current limit", style="bold yellow")
            self.query_one("#bars", Static).update(bars, layout=False)
        lines = []
        if self.solver is not None:
            lines.append(f"solve {self.solver.solve_time_us:7.1f} us   iterations "
                         f"{self.solver.iterations}   status {self.solver.status}")
        if self.loop_stats is not None:
            ls = self.loop_stats
            lines.append(f"tick median {ls.solve_median_us:.1f} us  p99 {ls.solve_p99_us:.1f} "
                         f"us  max {ls.solve_max_us:.1f} us")
            lines.append(f"jitter p99 {ls.period_jitter_p99_us:.1f} us  cycles {ls.cycles}  "
                         f"missed {ls.missed_cycles}  dropped {ls.dropped_messages}")
        lines.append(f"faults {self.faults}")
        self.query_one("#stats", Static).update("\n".join(lines), layout=False)

    def _show_joints(self, rows: list[JointRow]) -> None:
        table = self.query_one("#joints", DataTable)
        if [str(key.value) for key in table.rows] != [r.name for r in rows]:
            table.clear()
            for row in rows:
                table.add_row(*row_cells(row), key=row.name)
            return
        for row in rows:
            for column, cell in zip(table.ordered_columns, row_cells(row), strict=True):
                table.update_cell(row.name, column.key, cell)


def run_tui(session: zenoh.Session, prefix: str) -> None:
    feed = Feed(session, prefix)
    try:
        ElbowDashboard(feed, prefix).run()
    finally:
        feed.close()
