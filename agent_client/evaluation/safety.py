"""Surrogate safety measures of a driver's evaluation episodes, as the simulator reported them.

Our SUMO server takes them from SUMO's SSM device (docs/protocol.md §4.7): every conflict of
the ego, with its minimum time to collision (TTC), maximum deceleration to avoid a crash (DRAC),
post-encroachment time (PET), the time spent below the TTC threshold (time exposed TTC, TET)
and the time-integrated TTC (TIT). Here they become per-driver figures, normalised by the
distance driven so that drivers who go farther are not penalised for it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from protocol.messages import Conflict, Safety

if TYPE_CHECKING:
    from agent_client.evaluation.evaluate import EpisodeRecord

CRITICAL_TTC_S = 1.5
"""A conflict whose minimum TTC falls below this is serious (Van der Horst 1991; SUMO's own
threshold of 3 s defines a conflict at all)."""


def safety_figures(records: Sequence[EpisodeRecord]) -> dict[str, Any] | None:
    """The driver's SSM figures over the episodes that reported them; None if none did."""
    reported = [(r, r.safety) for r in records if r.safety is not None]
    if not reported:
        return None
    first: Safety = reported[0][1]
    conflicts = [c for _, safety in reported for c in safety.conflicts]
    km = sum(r.summary.distance for r, _ in reported) / 1000.0
    seconds = sum(r.summary.duration for r, _ in reported)
    min_ttcs = np.array([c.min_ttc for c in conflicts if c.min_ttc is not None])
    dracs = [c.max_drac for c in conflicts if c.max_drac is not None]
    pets = [c.min_pet for c in conflicts if c.min_pet is not None]
    exposed = sum(safety.ttc_below for _, safety in reported)  # overlapping conflicts once
    return {
        "episodes": len(reported),
        "thresholds": {
            "ttc_s": first.ttc_threshold,
            "drac": first.drac_threshold,
            "pet_s": first.pet_threshold,
            "critical_ttc_s": CRITICAL_TTC_S,
        },
        "distance_km": km,
        "conflicts": len(conflicts),
        "conflicts_per_km": len(conflicts) / km if km > 0 else None,
        "episodes_with_conflict": sum(bool(safety.conflicts) for _, safety in reported),
        "critical_conflicts": int((min_ttcs < CRITICAL_TTC_S).sum()),
        "min_ttc": float(min_ttcs.min()) if len(min_ttcs) else None,
        "median_conflict_min_ttc": float(np.median(min_ttcs)) if len(min_ttcs) else None,
        "max_drac": max(dracs) if dracs else None,
        "min_pet": min(pets) if pets else None,
        "ttc_exposed_s_per_km": exposed / km if km > 0 else None,
        "ttc_exposed_share": exposed / seconds if seconds > 0 else None,
        "ttc_integral_per_km": sum(c.ttc_integral for c in conflicts) / km if km > 0 else None,
        "drac_beyond_s_per_km": sum(c.drac_beyond for c in conflicts) / km if km > 0 else None,
        "conflict_min_ttcs": sorted(float(t) for t in min_ttcs),
        "per_episode_min_ttc": [_episode_min_ttc(s.conflicts) for _, s in reported],
    }


def _episode_min_ttc(conflicts: Sequence[Conflict]) -> float | None:
    values = [c.min_ttc for c in conflicts if c.min_ttc is not None]
    return min(values) if values else None
