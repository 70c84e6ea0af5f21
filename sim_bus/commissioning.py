"""A virtual drive set up for the joint it drives, as a commissioning tool would store it.

The shipped EDS describes the elbow's drive: its position window, rated and maximum current
and trip level are the elbow's. Behind any other joint those values would be wrong (a 12 A
leg joint refused by a 6 A drive, a wrist faulting at the elbow's window), so the embedding
stores these per joint, derived from the joint's model limits with the elbow's own margins:

- software position window 0x607D: the joint's limits widened by POSITION_WINDOW_MARGIN;
- rated current 0x6075 = current_max, max current 0x6073 = 1000 per mille of it;
- over-current trip 0x2003 = TRIP_FACTOR x current_max.

For the elbow these give back the EDS's own values.
"""

from model.parameters import Limits
from protocol import objects

# rad: the elbow EDS's window (-204435..8344 increments = -2.450..0.100 rad) around the
# paper's limits (-2.35..0 rad)
POSITION_WINDOW_MARGIN = 0.1
# the elbow EDS's trip level (8000 mA) over its max current (6000 mA)
TRIP_FACTOR = 4.0 / 3.0
FULL_SCALE = 1000  # per mille: max current 0x6073 equal to the rated current


def drive_settings(limits: Limits, increments_per_rad: float) -> dict[tuple[int, int], int]:
    """The object values (in the dictionary's units) that fit the drive to these limits."""
    return {
        (objects.SOFTWARE_POSITION_LIMIT, 1): objects.position_to_increments(
            limits.position_min - POSITION_WINDOW_MARGIN, increments_per_rad),
        (objects.SOFTWARE_POSITION_LIMIT, 2): objects.position_to_increments(
            limits.position_max + POSITION_WINDOW_MARGIN, increments_per_rad),
        (objects.RATED_CURRENT, 0): objects.amps_to_milliamps(limits.current_max),
        (objects.MAX_CURRENT, 0): FULL_SCALE,
        (objects.OVERCURRENT_TRIP, 0): objects.amps_to_milliamps(
            TRIP_FACTOR * limits.current_max),
    }
