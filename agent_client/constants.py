"""Physical constants and the thresholds of the paper's evaluation, in one place."""

from __future__ import annotations

KMH_PER_MS = 3.6
"""km/h in one m/s."""

PAPER_SPEED_LIMIT = 80 / KMH_PER_MS
"""m/s: the speed limit of the paper's road (80 km/h); the fallback when a server reports none."""

JERK_COMFORT_LIMIT = 5.6
"""m/s^3: jerk above this is uncomfortable (the paper's Fig. 10)."""

HEADWAY_SAFE = 1.0
"""s: time headways below this count as tailgating."""

TTC_CRITICAL = 4.0
"""s: times to collision below this count as critical."""

MIN_MOVING_SPEED = 0.1
"""m/s: below this a time headway is not defined."""
