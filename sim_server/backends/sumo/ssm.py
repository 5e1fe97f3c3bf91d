"""SUMO's surrogate safety measures for the ego: the SSM device's options and its conflict log.

The device (SUMO docs, "Simulation/Output/SSM_Device") follows every encounter of the ego with a
vehicle within its range and logs, when the encounter ends, the conflicts: encounters in which
time to collision (TTC), deceleration to avoid a crash (DRAC) or post-encroachment time (PET)
crossed its threshold, each with its per-step values. Its log is written as an XML file that
SUMO flushes when the simulation is closed or reloaded, so the backend reloads once at the end
of an episode and reads the log here into `protocol.messages.Safety`. Only the steps from the
client's hand-over on count (on the ring SUMO drives the ego through the warm-up).
"""

from __future__ import annotations

import math
from pathlib import Path
from xml.etree import ElementTree

from protocol.messages import Conflict, Safety

TTC_THRESHOLD_S = 3.0
"""A TTC below this is a conflict (SUMO's default; Van der Horst 1991 argues for 1.5 s)."""
DRAC_THRESHOLD = 3.0
"""m/s^2: a DRAC above this is a conflict (SUMO's default, after AASHTO 2004's 3.4 m/s^2)."""
PET_THRESHOLD_S = 2.0
"""A PET below this is a conflict (SUMO's default)."""


class LogError(ValueError):
    """The device's log is missing or cannot be read: the measures are unknown, not zero."""


def device_args(ego_id: str, log: Path) -> list[str]:
    """SUMO options that equip `ego_id` (only it) with the device, logging to `log`."""
    thresholds = f"{TTC_THRESHOLD_S:g} {DRAC_THRESHOLD:g} {PET_THRESHOLD_S:g}"
    return [
        "--device.ssm.explicit", ego_id,
        "--device.ssm.measures", "TTC DRAC PET",
        "--device.ssm.thresholds", thresholds,
        "--device.ssm.trajectories", "true",
        "--device.ssm.file", str(log),
    ]  # fmt: skip


def read_log(log: Path, step_length: float, since: float) -> Safety:
    """The conflicts of a closed simulation's SSM log, from simulation time `since` on."""
    try:
        root = ElementTree.parse(log).getroot()
    except (OSError, ElementTree.ParseError) as exc:
        raise LogError(f"SUMO's SSM log {log} could not be read: {exc}") from exc
    conflicts: list[Conflict] = []
    exposed: set[float] = set()
    for node in root.iter("conflict"):
        samples = _Samples.of(node, since)
        if samples.times:
            conflicts.append(samples.conflict(node, step_length))
            exposed.update(round(t, 6) for t, c in zip(samples.times, samples.ttcs, strict=True)
                           if c is not None and c < TTC_THRESHOLD_S)  # fmt: skip
    return Safety(
        tuple(conflicts),
        TTC_THRESHOLD_S,
        DRAC_THRESHOLD,
        PET_THRESHOLD_S,
        ttc_below=round(len(exposed) * step_length, 9),
    )


class _Samples:
    """A conflict's per-step TTC and DRAC from `since` on (None where undefined)."""

    def __init__(self, times: list[float], ttcs: list[float | None], dracs: list[float | None]):
        self.times, self.ttcs, self.dracs = times, ttcs, dracs

    @classmethod
    def of(cls, node: ElementTree.Element, since: float) -> _Samples:
        times = [float(t) for t in _values(node, "timeSpan")]
        ttcs, dracs = _values(node, "TTCSpan"), _values(node, "DRACSpan")
        if len(ttcs) != len(times) or len(dracs) != len(times):
            raise LogError("SUMO's SSM log has spans of different lengths: was it cut short?")
        kept = [i for i, t in enumerate(times) if t >= since - 1e-9]
        return cls(
            [times[i] for i in kept], [_number(ttcs[i]) for i in kept],
            [_number(dracs[i]) for i in kept],
        )  # fmt: skip

    def conflict(self, node: ElementTree.Element, step_length: float) -> Conflict:
        ttcs = [t for t in self.ttcs if t is not None]
        dracs = [d for d in self.dracs if d is not None]
        below = [TTC_THRESHOLD_S - t for t in ttcs if t < TTC_THRESHOLD_S]
        return Conflict(
            foe=node.get("foe", ""),
            begin=self.times[0],
            end=self.times[-1],
            min_ttc=min(ttcs) if ttcs else None,
            max_drac=max(dracs) if dracs else None,
            min_pet=_pet(node, self.times[0]),
            ttc_below=round(len(below) * step_length, 9),
            drac_beyond=round(sum(1 for d in dracs if d > DRAC_THRESHOLD) * step_length, 9),
            ttc_integral=round(sum(below) * step_length, 9),
        )


def _values(node: ElementTree.Element, tag: str) -> list[str]:
    found = node.find(tag)
    return [] if found is None else found.get("values", "").split()


def _number(text: str) -> float | None:
    """A span's value; None for SUMO's "NA" (the measure is undefined at that step)."""
    if text == "NA":
        return None
    value = float(text)
    return value if math.isfinite(value) else None


def _pet(node: ElementTree.Element, since: float) -> float | None:
    """The conflict's PET, if it was measured at or after `since`."""
    found = node.find("PET")
    if found is None or found.get("time", "NA") == "NA":
        return None
    value = _number(found.get("value", "NA"))
    return value if float(found.get("time", "0")) >= since - 1e-9 else None
