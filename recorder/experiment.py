"""Run a reference trajectory on a drive and hand every sample to a sink."""

from collections.abc import Callable

from driver import Drive, Sample
from driver.clock import CycleClock
from recorder.exciting import ExcitingTrajectory, SlowSinusoid
from recorder.tracking import TrackingLaw

SampleSink = Callable[[Sample, float, tuple[float, float, float]], None]


def run_trajectory(drive: Drive, trajectory: ExcitingTrajectory | SlowSinusoid, law: TrackingLaw,
                            sink: SampleSink, lockstep: bool,
                            progress: Callable[[float], None] = lambda fraction: None,
                            should_stop: Callable[[], bool] = lambda: False) -> int:
    """Track the trajectory from the drive's time 0 to its end; returns the samples taken.
    The drive must be started (enabled); the caller closes it."""
    clock = CycleClock(drive.period, lockstep)
    duration = trajectory.duration
    samples = 0
    t0 = None
    while not should_stop():
        clock.wait()
        sample = drive.sync()
        if t0 is None:
            t0 = sample.t
        t = sample.t - t0
        reference = trajectory.sample(t)
        current = law.current(sample.position, sample.velocity, reference)
        drive.command_current(current)
        sink(sample, current, reference)
        samples += 1
        if samples % 500 == 0:
            progress(min(t / duration, 1.0))
        if t >= duration:
            break
    progress(1.0)
    return samples
