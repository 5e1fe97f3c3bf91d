"""The highway scenarios: ``cf`` and ``cflc`` on highway-env's straight road, and every scenario
the backend offers (`SCENARIOS`), the corridors (`corridors.py`) included.

Every road is populated with highway-env's own human drivers (`IDMVehicle`: IDM car following,
MOBIL lane changing).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from highway_env.road.road import Road as HighwayRoad
from highway_env.utils import near_split
from highway_env.vehicle.behavior import IDMVehicle

from protocol.messages import OptionValue, ScenarioInfo
from sim_server.backends.highway.corridors import CorridorScenario
from sim_server.backends.highway.networks import straight_layout
from sim_server.backends.highway.scene import DT, HONOURED, Scene, SceneOptions
from sim_server.backends.options import COMMON_OPTIONS


@dataclass(frozen=True)
class HighwayScenario:
    """A straight road with highway-env human traffic on every lane."""

    name: str
    description: str
    lanes: int
    length: float = 2000.0
    speed_limit: float = 80 / 3.6
    defaults: dict[str, OptionValue] = field(default_factory=dict)

    def info(self) -> ScenarioInfo:
        options: dict[str, OptionValue] = {name: COMMON_OPTIONS[name] for name in HONOURED}
        options.update(warmup=5.0, **SceneOptions().as_options())
        options.update(self.defaults)
        return ScenarioInfo(self.name, self.description, options, DT)

    def build(self, seed: int, options: Mapping[str, OptionValue], names: tuple[str, ...]) -> Scene:
        """The road and its vehicles, placed by highway-env's ``create_random``: `vehicles_behind`
        humans, then each ego of `names` followed by its share of the other humans (highway-env's
        ``near_split``, as its ``_create_vehicles`` places ``controlled_vehicles``)."""
        scene = SceneOptions.parse(options)
        layout = straight_layout(self.lanes, self.length, self.speed_limit)
        road = HighwayRoad(
            network=layout.network, np_random=np.random.default_rng(seed), record_history=False
        )
        spacing = 1.0 / scene.vehicles_density
        shares = near_split(scene.vehicles_count - scene.vehicles_behind, num_bins=len(names))
        plan: list[str | None] = [None] * scene.vehicles_behind
        for name, share in zip(names, shares, strict=True):
            plan += [name, *[None] * int(share)]
        ids: dict[Any, str] = {}
        egos: dict[str, Any] = {}
        for role in plan:
            vehicle = IDMVehicle.create_random(road, spacing=spacing)
            vehicle.randomize_behavior()
            road.vehicles.append(vehicle)
            if role is None:
                ids[vehicle] = f"h{len(ids) - len(egos)}"
            else:
                ids[vehicle], egos[role] = role, vehicle
        return Scene(road, layout, ids, [egos[name] for name in names])


Scenario = HighwayScenario | CorridorScenario


_CORRIDOR_TRAFFIC: dict[str, OptionValue] = {
    "vehicles_count": 16,
    "vehicles_behind": 4,
    "vehicles_density": 0.5,
}
"""The corridors' humans: ~100-160 m apart in each lane (~470-730 veh/h/lane), sparse enough that
highway-env's MOBIL, with its 2 m/s² safety rule and IDM's 1.5 s time gap, finds gaps to merge
into; at ``vehicles_density`` 0.7 humans often stand at the end of the acceleration lane."""

SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        HighwayScenario(
            "cf",
            "highway-env car following: 2 km single lane, 80 km/h, IDM human traffic ahead",
            lanes=1,
        ),
        HighwayScenario(
            "cflc",
            "highway-env car following and lane changing: 2 km, 3 lanes, 80 km/h, IDM/MOBIL "
            "human traffic",
            lanes=3,
            defaults={"vehicles_count": 20, "vehicles_behind": 4, "vehicles_density": 0.7},
        ),
        CorridorScenario(
            "merge",
            "highway-env on-ramp: the ego enters from a ramp and must merge from its "
            "acceleration lane onto a motorway of 2-3 lanes (100 km/h, IDM/MOBIL human traffic); "
            "geometry drawn per seed",
            "merge",
            defaults=_CORRIDOR_TRAFFIC,
        ),
        CorridorScenario(
            "exit",
            "highway-env exit: the ego's route leaves a motorway of 2-4 lanes by an off-ramp on "
            "the right, 600-1200 m ahead after a deceleration lane; it starts in any lane; "
            "drawn per seed",
            "exit",
            defaults=_CORRIDOR_TRAFFIC,
        ),
        CorridorScenario(
            "lanedrop",
            "highway-env lane drop: three motorway lanes become two, the left or the right one "
            "ending 400-1000 m ahead; the ego starts in any lane; drawn per seed",
            "lanedrop",
            defaults=_CORRIDOR_TRAFFIC,
        ),
    )
}
