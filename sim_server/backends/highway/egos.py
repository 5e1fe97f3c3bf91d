"""The book-keeping of a highway episode, for one ego and for many: the running scene
(`Episode`), each ego of a multi-ego episode (`Driven`) and its part of a decision (`Turn`), and
the client's vehicle that replaces an ego's human model at the hand-over (`ClientVehicle`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from protocol.messages import AppliedAction, Events, Observation
from sim_server.backends.highway.road import Layout
from sim_server.backends.highway.scenarios import Scenario
from sim_server.backends.highway.scene import SIMULATION_FREQUENCY
from sim_server.backends.options import EpisodeOptions
from sim_server.backends.rules import EndRule, LaneChangeUnderWay


class ClientVehicle(ControlledVehicle):  # type: ignore[misc]
    """The client's ego: highway-env's lateral controller, the client's acceleration."""

    command: float = 0.0

    def act(self, action: Any = None) -> None:
        self.follow_road()
        steering = self.steering_control(self.target_lane_index)
        steering = float(np.clip(steering, -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE))
        Vehicle.act(self, {"steering": steering, "acceleration": self.command})


@dataclass
class Driven:
    """One ego of a multi-ego episode and its own book-keeping (a one-ego episode keeps its
    ego's in `Episode`)."""

    id: str
    vehicle: Any
    end: EndRule
    lane_change: LaneChangeUnderWay | None = None
    over: bool = False
    """Its drive has ended (reported once, then off the road)."""


@dataclass
class Turn:
    """One ego's part of a decision of a multi-ego episode."""

    driven: Driven
    request: float
    lane_change: int
    refused: str
    started: bool
    applied_total: float = 0.0
    limited_by: str = ""
    why: str = ""
    """What limited the acceleration on the current simulation step."""
    steps: int = 0
    """Simulation steps driven in this decision."""
    collision_with: str = ""
    end_of_road: bool = False
    lane_end: bool = False
    """Its front passed the end of its lane (`Layout.past_lane_end`): it ends with
    ``lane_end``."""
    completed: bool = False
    aborted: bool = False
    last: Observation | None = None
    """Observed at the simulation step where its drive ended inside the decision."""

    @property
    def stopped_inside(self) -> bool:
        return bool(self.collision_with) or self.end_of_road or self.lane_end

    def result(self) -> tuple[AppliedAction, Events]:
        action = AppliedAction(
            requested_acceleration=self.request,
            requested_lane_change=self.lane_change,
            acceleration=self.applied_total / self.steps,
            lane_change=0 if self.refused else self.lane_change,
            acceleration_limited_by=self.limited_by,
            lane_change_refused=self.refused,
        )
        events = Events(
            collision=bool(self.collision_with),
            collision_with=self.collision_with,
            end_of_road=self.end_of_road,
            lane_change_started=self.started,
            lane_change_completed=self.completed,
            lane_change_refused=bool(self.refused),
            lane_change_aborted=self.aborted,
        )
        return action, events


@dataclass
class Episode:
    """The running scene and its book-keeping."""

    scenario: Scenario
    road: Any
    layout: Layout
    ego: Any
    options: EpisodeOptions
    substeps: int
    ids: dict[Any, str]
    spawn_front: dict[Any, float]
    steps: int = 0
    leader: Any = None
    leader_arrival: float | None = None
    leader_end: float = 0.0
    """Route coordinate of the end of the road where the leader-at-entry arrived."""
    stranded: dict[Any, float] = field(default_factory=dict)
    """Humans standing at the end of a lane that ends, and since when (`simulation.stranded`)."""
    lane_change: LaneChangeUnderWay | None = None
    collided: Any = None
    done: bool = False
    fleet: list[Driven] = field(default_factory=list)
    """The egos of a multi-ego episode, in highway-env's ``controlled_vehicles`` order (then
    `ego` is None); empty in a one-ego episode."""
    end: EndRule = field(init=False)
    """Set at the hand-over: the episode's time runs from there."""

    @property
    def time(self) -> float:
        return self.steps / SIMULATION_FREQUENCY

    def egos(self) -> list[Any]:
        """The ego vehicles on the road: the one ego, or the fleet's still driving."""
        if not self.fleet:
            return [self.ego]
        return [d.vehicle for d in self.fleet if not d.over]
