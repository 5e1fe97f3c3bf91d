"""The corridors with a lane end: ``merge`` (an on-ramp), ``exit`` (an off-ramp on the right)
and ``lanedrop`` (three lanes become two), and their options.

Each corridor's geometry is drawn from the seed from the SUMO corridors' grids, in the same order
of draws (`sumo.corridors`): the same seed and options give the same lengths and lanes on both
servers; each option of the geometry fixes it instead when set. The road is built by
`networks.py`, its vehicles placed by `placement.py`.
"""

from __future__ import annotations

import random
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from protocol.messages import OptionValue, ScenarioInfo
from sim_server.backends.highway.networks import LANE_DROP_LANES, Geometry
from sim_server.backends.highway.placement import exit_scene, lane_drop_scene, merge_scene
from sim_server.backends.highway.scene import DT, HONOURED, Scene, SceneOptions
from sim_server.backends.options import COMMON_OPTIONS, Bounds, ParsedOptions, invalid_option
from sim_server.backends.sumo.corridors import (
    ACCELERATION_LANES,
    DECELERATION_LANES,
    DROP_DISTANCES,
    DROPPED_LANES,
    EXIT_DISTANCES,
    EXIT_LANES,
    MERGE_LANES,
    MOTORWAY_SPEED,
    RAMP_LENGTHS,
)


@dataclass(frozen=True, slots=True)
class MergeOptions(ParsedOptions):
    """The on-ramp (the SUMO corridor's names): 0 draws a value per seed, anything else fixes
    it."""

    main_lanes: int = 0
    """Lanes of the motorway, 2 or 3 (0: drawn)."""
    acceleration_lane: float = 0.0
    """Length of the acceleration lane (m; 0: drawn from 150-300 m)."""
    ramp_length: float = 0.0
    """Length of the ramp before it (m; 0: drawn from 150-350 m)."""
    ramp_vehicles: int = 2
    """Humans on the ramp ahead of the ego, as many as fit on it (SUMO's ``ramp_flow`` instead:
    highway-env's traffic is placed at reset, it does not flow in)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "main_lanes": Bounds(0, 3, text="0 (drawn), 2 or 3"),
        "acceleration_lane": Bounds(0.0, 2000.0, unit=" m"),
        "ramp_length": Bounds(0.0, 2000.0, unit=" m"),
        "ramp_vehicles": Bounds(0, 20),
    }

    def check(self) -> None:
        if self.main_lanes == 1:
            raise invalid_option("option main_lanes must be 0 (drawn), 2 or 3")
        if 0 < self.acceleration_lane < 20 or 0 < self.ramp_length < 20:
            raise invalid_option("options acceleration_lane and ramp_length must be 0 or >= 20 m")


@dataclass(frozen=True, slots=True)
class ExitOptions(ParsedOptions):
    """The exit (the SUMO corridor's names): 0 draws a value per seed, anything else fixes it."""

    main_lanes: int = 0
    """Lanes of the motorway, 2 to 4 (0: drawn)."""
    exit_distance: float = 0.0
    """Metres from the ego's front at reset (the frontmost ego's) to where the off-ramp leaves
    (0: drawn from 600-1200 m)."""
    deceleration_lane: float = 0.0
    """Length of the deceleration lane before it (m; 0: drawn, 100 or 200 m)."""
    ego_lane: int = -1
    """The ego's lane at its start, 0 the rightmost (-1: random; one beyond the motorway's
    lanes is its leftmost)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "main_lanes": Bounds(0, 4, text="0 (drawn), 2, 3 or 4"),
        "exit_distance": Bounds(0.0, 10_000.0, unit=" m"),
        "deceleration_lane": Bounds(0.0, 1000.0, unit=" m"),
        "ego_lane": Bounds(-1, 3),
    }

    def check(self) -> None:
        if self.main_lanes == 1:
            raise invalid_option("option main_lanes must be 0 (drawn), 2, 3 or 4")
        if 0 < self.deceleration_lane < 20:
            raise invalid_option("option deceleration_lane must be 0 or >= 20 m")


@dataclass(frozen=True, slots=True)
class LaneDropOptions(ParsedOptions):
    """The lane drop (the SUMO corridor's names): 0 (or ``random``) draws a value per seed,
    anything else fixes it."""

    drop_distance: float = 0.0
    """Metres from the ego's front at reset (the frontmost ego's) to where the lane ends (0:
    drawn from 400-1000 m)."""
    dropped_lane: str = "random"
    """Which of the three lanes ends: ``left``, ``right`` or ``random`` (drawn)."""
    ego_lane: int = -1
    """The ego's lane at its start, 0 the rightmost (-1: random)."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "drop_distance": Bounds(0.0, 10_000.0, unit=" m"),
        "ego_lane": Bounds(-1, 2),
    }

    def check(self) -> None:
        if 0 < self.drop_distance < 100:
            raise invalid_option("option drop_distance must be 0 or >= 100 m")
        valid = ("random", *DROPPED_LANES)
        if self.dropped_lane not in valid:
            raise invalid_option(
                f"option dropped_lane must be one of {', '.join(valid)}, "
                f"got {self.dropped_lane[:64]!r}"
            )


@dataclass(frozen=True)
class CorridorScenario:
    """A motorway corridor with a lane end (`kind`: ``merge``, ``exit`` or ``lanedrop``), its
    geometry drawn from the seed as the SUMO corridors draw theirs (the same grids, the same
    order of draws, so the same seed and options give the same lengths and lanes)."""

    name: str
    description: str
    kind: str
    defaults: dict[str, OptionValue] = field(default_factory=dict)
    speed_limit: float = MOTORWAY_SPEED

    OPTIONS: ClassVar[dict[str, type[ParsedOptions]]] = {
        "merge": MergeOptions,
        "exit": ExitOptions,
        "lanedrop": LaneDropOptions,
    }

    def info(self) -> ScenarioInfo:
        options: dict[str, OptionValue] = {name: COMMON_OPTIONS[name] for name in HONOURED}
        options.update(warmup=5.0, **SceneOptions().as_options())
        options.update(self.OPTIONS[self.kind]().as_options())
        options.update(self.defaults)
        return ScenarioInfo(self.name, self.description, options, DT)

    def geometry(self, seed: int, options: Mapping[str, OptionValue]) -> Geometry:
        """The geometry `seed` draws, with `options` fixing what they set: the SUMO corridors'
        draws (`sumo.corridors`), from the same grids in the same order."""
        own = self.OPTIONS[self.kind].parse(options)
        draw = random.Random(f"{self.kind}:{seed}")
        if isinstance(own, MergeOptions):
            lanes = own.main_lanes or draw.choice(MERGE_LANES)
            acceleration = own.acceleration_lane or draw.choice(ACCELERATION_LANES)
            ramp = own.ramp_length or draw.choice(RAMP_LENGTHS)
            return Geometry(lanes, ramp_length=ramp, acceleration_lane=acceleration)
        if isinstance(own, ExitOptions):
            lanes = own.main_lanes or draw.choice(EXIT_LANES)
            distance = own.exit_distance or draw.choice(EXIT_DISTANCES)
            deceleration = own.deceleration_lane or draw.choice(DECELERATION_LANES)
            if distance < deceleration + 100.0:  # as the SUMO corridor
                raise invalid_option(
                    "option exit_distance must leave at least 100 m before the deceleration lane"
                )
            return Geometry(lanes, exit_distance=distance, deceleration_lane=deceleration)
        assert isinstance(own, LaneDropOptions)
        distance = own.drop_distance or draw.choice(DROP_DISTANCES)
        dropped = own.dropped_lane if own.dropped_lane != "random" else draw.choice(DROPPED_LANES)
        return Geometry(LANE_DROP_LANES, drop_distance=distance, dropped_lane=dropped)

    def build(self, seed: int, options: Mapping[str, OptionValue], names: tuple[str, ...]) -> Scene:
        """The corridor `seed` draws (`geometry`), and its vehicles:
        humans one after another on the motorway as ``create_random`` spaces them,
        `vehicles_behind` of them behind the egos' start; on ``merge`` the egos one after another
        on the ramp (then ``ramp_vehicles`` humans), elsewhere each ego followed by its share of
        the humans, as on ``cf``. The egos keep their lane during the warm-up (lane changes are
        the client's)."""
        scene = SceneOptions.parse(options)
        own = self.OPTIONS[self.kind].parse(options)
        geometry = self.geometry(seed, options)
        rng = np.random.default_rng(seed)
        if isinstance(own, MergeOptions):
            return merge_scene(geometry, own.ramp_vehicles, scene, rng, names)
        assert isinstance(own, ExitOptions | LaneDropOptions)
        scene_of = exit_scene if isinstance(own, ExitOptions) else lane_drop_scene
        return scene_of(geometry, own.ego_lane, scene, rng, names)
