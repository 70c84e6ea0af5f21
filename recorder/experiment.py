"""Run an experiment's trajectory on a drive through the control loop, handing every message
to the recording's subscribers."""

import threading
from collections.abc import Callable, Sequence

from controller import messages
from controller.loop import ControlLoop, Joints, LoopOptions, LoopReport
from controller.messages import Subscriber, WireSubscriber
from driver.clock import DriveClock, WallClock
from model.parameters import Limits
from recorder.tracking import TrackingLaw, TrackingPolicy, Trajectory

PROGRESS_EVERY = 500  # samples between progress updates


def run_trajectory(joint: Joints, trajectory: Trajectory, law: TrackingLaw, limits: Limits,
                   subscribers: Sequence[Subscriber], clock: WallClock | DriveClock,
                   progress: Callable[[float], None] = lambda fraction: None,
                   stop: threading.Event | None = None,
                   wire_subscribers: Sequence[WireSubscriber] = ()) -> LoopReport:
    """Track the trajectory from the drive's first sample to its end (or until `stop` is set);
    report.cycles is the number of samples taken. `joint` is a robot of one, started
    (enabled), on `clock` (drive time in lock-step); the caller closes it. `subscribers` get
    the messages, `wire_subscribers` their bytes (`ControlLoop`'s): a recording that only
    writes bytes has no message built for it."""
    policy = TrackingPolicy(trajectory, law, limits)
    duration = trajectory.duration

    def follow(message) -> None:  # a wire subscriber: each cycle's view comes as its bytes
        if type(message) is messages.EncodedJointView and (
                loop.report.cycles % PROGRESS_EVERY == 0):
            progress(min(policy.elapsed(message.t) / duration, 1.0))

    loop = ControlLoop(joint, policy, LoopOptions(period=joint.period, clock=clock),
                       subscribers, stop=stop, wire_subscribers=[*wire_subscribers, follow])
    report = loop.run()
    progress(1.0)
    return report
