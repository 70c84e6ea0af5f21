"""Is actuatord still there? Each actuatord holds a Zenoh liveliness token at {prefix}/alive;
Zenoh withdraws it when the process ends or its link drops, even on SIGKILL, where no last
message could say so. Silence on the telemetry topics alone cannot tell a dead publisher from
a paused one."""

from collections.abc import Callable

import zenoh

from protocol import telemetry


def watch_publisher(session: zenoh.Session, prefix: str,
                    on_change: Callable[[bool], None]) -> zenoh.Subscriber:
    """Calls on_change(True) when actuatord's token appears (at once if it already exists) and
    on_change(False) when it goes. Undeclare the returned subscriber to stop watching."""
    return session.liveliness().declare_subscriber(
        telemetry.key_expr(prefix, telemetry.LIVELINESS),
        lambda sample: on_change(sample.kind == zenoh.SampleKind.PUT), history=True)
