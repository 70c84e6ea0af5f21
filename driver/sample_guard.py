"""Plausibility of a drive's samples, with the joint's limits passed in: a sample is physics,
not a transport's business, and each joint has its own limits."""

from dataclasses import dataclass

from driver.interface import EncoderGlitch
from protocol import cia301

# a step this many times what the velocity limit allows in one period is not motion: it
# leaves room for overshoot past the limit while a 5000-increment glitch still stands out
GLITCH_FACTOR = 4.0


@dataclass(frozen=True)
class SampleGuard:
    """`velocity_limit` (rad/s, the joint's) and `period` (s) bound the position step per
    cycle; a sensor reading pinned at its INT32 limit is saturated, not a measurement."""

    velocity_limit: float
    period: float

    @property
    def max_position_step(self) -> float:
        return GLITCH_FACTOR * self.velocity_limit * self.period

    def check_step(self, previous: float, position: float, name: str, cycles: int = 1) -> None:
        """EncoderGlitch if the position jumped further than the joint can move in `cycles`
        periods (more than one when the drive's own clock ran on between the two samples:
        distributed clocks while the master was late)."""
        step = position - previous
        if abs(step) > self.max_position_step * cycles:
            within = "in one cycle" if cycles == 1 else f"in {cycles} cycles"
            raise EncoderGlitch(f"{name}: position jumped {step:+.4f} rad {within} (at most "
                                f"{self.max_position_step * cycles:.4f} rad is motion): "
                                "encoder glitch")

    @staticmethod
    def saturated(reading: int) -> bool:
        return reading >= cia301.INT32_MAX or reading <= cia301.INT32_MIN
