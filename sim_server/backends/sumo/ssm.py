"""SUMO's surrogate safety measures for the ego: the SSM device's options and its conflict log.

The device (SUMO docs, "Simulation/Output/SSM_Device") follows every encounter of the ego with a
vehicle within its range and logs, when the encounter ends, the conflicts: encounters in which
time to collision (TTC), deceleration to avoid a crash (DRAC) or post-encroachment time (PET)
crossed its threshold, each with its per-step values. Its log is written as an XML file that
SUMO flushes when the simulation is closed or reloaded, so the backend reloads once at the end
of an episode and reads the log here into `protocol.messages.Safety`.
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


def read_log(log: Path, step_length: float) -> Safety:
    """The conflicts of a closed simulation's SSM log (none if the device logged nothing)."""
    conflicts: tuple[Conflict, ...] = ()
    if log.is_file() and log.stat().st_size:
        root = ElementTree.parse(log).getroot()
        conflicts = tuple(_conflict(node, step_length) for node in root.iter("conflict"))
    return Safety(conflicts, TTC_THRESHOLD_S, DRAC_THRESHOLD, PET_THRESHOLD_S)


def _conflict(node: ElementTree.Element, step_length: float) -> Conflict:
    ttcs = _span(node, "TTCSpan")
    dracs = _span(node, "DRACSpan")
    below = [TTC_THRESHOLD_S - t for t in ttcs if t < TTC_THRESHOLD_S]
    return Conflict(
        foe=node.get("foe", ""),
        begin=float(node.get("begin", "nan")),
        end=float(node.get("end", "nan")),
        min_ttc=_extreme(node, "minTTC"),
        max_drac=_extreme(node, "maxDRAC"),
        min_pet=_extreme(node, "PET"),
        ttc_below=round(len(below) * step_length, 9),
        drac_beyond=round(sum(1 for d in dracs if d > DRAC_THRESHOLD) * step_length, 9),
        ttc_integral=round(sum(below) * step_length, 9),
    )


def _span(node: ElementTree.Element, tag: str) -> list[float]:
    """The defined values of a per-step span ("NA" where the measure is undefined)."""
    found = node.find(tag)
    values = "" if found is None else found.get("values", "")
    return [float(v) for v in values.split() if v != "NA"]


def _extreme(node: ElementTree.Element, tag: str) -> float | None:
    found = node.find(tag)
    value = None if found is None else found.get("value")
    if value is None or value == "NA":
        return None
    number = float(value)
    return number if math.isfinite(number) else None
