"""`dashboard tui`: the actuator at a glance in a terminal on the robot. Live values, position
and current against their limits as bars, solver and loop statistics, faults highlighted, and a
short scrolling plot of position and current."""

from collections import deque

from rich.text import Text
from textual.app import App, ComposeResult
from textual.containers import Horizontal, Vertical
from textual.widgets import Footer, Header, Log, Sparkline, Static

from protocol import telemetry

HISTORY = 200  # points in the scrolling plots
BAR_WIDTH = 40


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


class ElbowDashboard(App):
    CSS = """
    #values { height: 7; border: round $accent; padding: 0 1; }
    #bars { height: 6; border: round $accent; padding: 0 1; }
    #stats { height: 5; border: round $accent; padding: 0 1; }
    #plots { height: 7; }
    .plot { width: 1fr; height: 7; border: round $accent; }
    #faults { height: 1fr; border: round red; }
    """
    BINDINGS = [("q", "quit", "quit")]

    def __init__(self, prefix: str = telemetry.DEFAULT_PREFIX):
        super().__init__()
        self.prefix = prefix
        self.title = f"actuator-link: {prefix}"
        self.positions: deque[float] = deque(maxlen=HISTORY)
        self.currents: deque[float] = deque(maxlen=HISTORY)
        self.state = None
        self.command = None
        self.solver = None
        self.loop_stats = None
        self.faults = 0

    def compose(self) -> ComposeResult:
        yield Header()
        with Vertical():
            yield Static(id="values")
            yield Static(id="bars")
            yield Static(id="stats")
            with Horizontal(id="plots"):
                yield Sparkline([], id="position_plot", classes="plot")
                yield Sparkline([], id="current_plot", classes="plot")
            yield Log(id="faults")
        yield Footer()

    def on_mount(self) -> None:
        self.query_one("#values", Static).border_title = "live"
        self.query_one("#bars", Static).border_title = "limits"
        self.query_one("#stats", Static).border_title = "solver and loop"
        self.query_one("#position_plot", Sparkline).border_title = "position"
        self.query_one("#current_plot", Sparkline).border_title = "current"
        self.query_one("#faults", Log).border_title = "faults"
        self.refresh_view()

    def ingest(self, topic: str, message) -> None:
        """Take one decoded telemetry message (call on the app's thread)."""
        if topic == "state":
            self.state = message
            self.positions.append(message.position)
            self.currents.append(message.motor_current)
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
        self.refresh_view()

    def refresh_view(self) -> None:
        s, c = self.state, self.command
        if s is None:
            self.query_one("#values", Static).update(f"waiting for {self.prefix}/state ...")
            return
        reference = f"{c.reference_position:+.3f}" if c else "?"
        self.query_one("#values", Static).update(
            f"t {s.t:10.3f} s   drive: {s.drive_state}\n"
            f"position {s.position:+.4f} rad   reference {reference} rad\n"
            f"velocity {s.velocity:+.4f} rad/s\n"
            f"current  {s.motor_current:+.3f} A   commanded "
            f"{(c.current if c else float('nan')):+.3f} A\n"
            f"joint torque {s.joint_torque:+.3f} N.m")
        if c is not None:
            bars = Text("position ")
            bars.append(limit_bar(s.position, c.position_min, c.position_max))
            bars.append("\ncurrent  ")
            bars.append(limit_bar(s.motor_current, -c.current_limit, c.current_limit))
            if c.fallback:
                bars.append("\nSAFETY FALLBACK ACTIVE", style="bold white on red")
            elif c.saturated:
                bars.append("\ncommand saturated at the current limit", style="bold yellow")
            self.query_one("#bars", Static).update(bars)
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
        self.query_one("#stats", Static).update("\n".join(lines))
        self.query_one("#position_plot", Sparkline).data = list(self.positions)
        self.query_one("#current_plot", Sparkline).data = list(self.currents)


def run_tui(session, prefix: str) -> None:
    app = ElbowDashboard(prefix)
    classes = {topic: telemetry.message_class(name) for topic, name in telemetry.TOPICS.items()}

    def on_sample(sample) -> None:
        topic = str(sample.key_expr).rsplit("/", 1)[-1]
        if topic in classes:
            message = classes[topic]()
            message.ParseFromString(sample.payload.to_bytes())
            if topic == "state" and message.t % 0.05 > 1e-3:  # 20 Hz is plenty for eyes
                return
            app.call_from_thread(app.ingest, topic, message)

    subscriber = session.declare_subscriber(f"{prefix}/*", on_sample)
    try:
        app.run()
    finally:
        subscriber.undeclare()
