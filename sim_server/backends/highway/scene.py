"""What every highway scenario shares: the simulation clock, the common options it honours, how
highway-env's ``create_random`` places its humans (`SceneOptions`), and the scene it builds: a
road with its vehicles placed, before the warm-up (`Scene`)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from sim_server.backends.highway.road import Layout
from sim_server.backends.options import Bounds, ParsedOptions, invalid_option

SIMULATION_FREQUENCY = 10
"""Simulation steps per second (highway-env's ``simulation_frequency``)."""
DT = 1.0 / SIMULATION_FREQUENCY

HONOURED = (
    "decision_interval",
    "max_episode_time",
    "warmup",
    "stop_speed",
    "stop_gap",
    "stop_patience",
    "lane_end_patience",
    "report_ceiling",
    "ego_driver",
    "egos",
)
"""The SUMO server's common options this backend honours: the same meaning, except that during
the ``warmup`` highway-env's own human model drives the ego (it is on the road from the start)."""


@dataclass(frozen=True, slots=True)
class SceneOptions(ParsedOptions):
    """How highway-env's ``create_random`` places the humans: `vehicles_behind` of them behind
    the ego, the rest ahead, one ``1 / vehicles_density`` spacing apart."""

    vehicles_count: int = 12
    """Human vehicles (highway-env's ``vehicles_count``)."""
    vehicles_behind: int = 2
    """Of which placed behind the ego, at most `vehicles_count`."""
    vehicles_density: float = 0.6
    """highway-env's ``vehicles_density``."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "vehicles_count": Bounds(0, 200, text="in 0..200"),
        "vehicles_density": Bounds(0.05, 10.0, text="within [0.05, 10]"),
    }

    def check(self) -> None:
        if not 0 <= self.vehicles_behind <= self.vehicles_count:
            raise invalid_option("option vehicles_behind must be in 0..vehicles_count")


@dataclass
class Scene:
    """A scenario's road with its vehicles placed, before the warm-up."""

    road: Any
    layout: Layout
    ids: dict[Any, str]
    """Every vehicle's id: ``h0``, ``h1``... for the humans in spawn order, the egos' names."""
    egos: list[Any]
    """The egos' vehicles, in the order of their names."""
