"""The per-ego book-keeping of `SumoBackend`, for one ego and for many in one simulation.

Every ego, the one of a one-ego episode (id ``ego``) and each of a multi-ego episode (protocol
1.4: ``ego.0``, ``ego.1``, ...), has an `EgoState`: its own end rule, the lane change it has
under way and its last observation. A decision being simulated is a `Drive` per ego, which
collects what happened over the decision's simulation steps and turns it into the observation's
`AppliedAction` and `Events`. The one-ego and the multi-ego paths share both, so an ego is
judged the same way whether it drives alone or among others. With ``ego_share`` (protocol 1.5)
a `ShareDraw` picks the vehicles that become egos.
"""

from __future__ import annotations

import math
import random
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from protocol.messages import (
    ROAD_RANGE,
    AppliedAction,
    CollisionType,
    EndReason,
    Events,
    MultiObservation,
    Observation,
    Traffic,
)
from sim_server.backends.base import ego_part
from sim_server.backends.rules import EndRule, LaneChangeUnderWay
from sim_server.backends.sumo.signals import RedLightWatch

EGO_ID_PREFIX = "ego."
"""The egos of a multi-ego episode are ``ego.0``, ``ego.1``, ... in the order they entered."""

QUIET = Events()
"""The events of most steps (nothing happened); immutable, so shared."""


def ego_ids(count: int) -> tuple[str, ...]:
    """The SUMO vehicle ids of a multi-ego episode's `count` egos, in the order they enter."""
    return tuple(f"{EGO_ID_PREFIX}{k}" for k in range(count))


@dataclass(slots=True)
class EgoState:
    """One ego's book-keeping during an episode."""

    id: str
    """Its SUMO vehicle id, also its id on the wire."""
    end: EndRule
    """When its drive ends (its own stop timer; the entry time is the hand-over)."""
    entry_offset: float
    """Its front's position on its route when it entered (ring: its place on the ring at
    reset); `Ego.position` is this plus SUMO's odometer."""
    min_gap: float
    """Its minGap, which SUMO's leader distances leave out."""
    lane_change: LaneChangeUnderWay | None = None
    last: Observation | None = None
    """Its latest observation: extrapolated when it leaves the network."""
    route: tuple[str, ...] = ()
    """The edges of its route, reported on its first and last observation (not on the ring)."""
    route_index: int = 0
    """The edge of its route it was on at its latest observation (0: the first)."""
    approach_lane: str = ""
    """The last lane it was on outside a junction (where its way through the junction
    began)."""
    red_lights: RedLightWatch = field(default_factory=RedLightWatch)
    """Whether it crosses a red stop line (networks with traffic lights only)."""
    give_way: float = ROAD_RANGE
    """m to the next junction where it has no priority (gives way, or a permissive green) at
    its latest observation; ROAD_RANGE where it has priority, or none is ahead."""
    across: float = 0.0
    """m to the far side of the next junction (its lane's end and the junction's lane) at its
    latest observation, within 50 m of it; 0 where none is that near."""


class Drive:
    """One ego's decision being simulated: the command, its verdicts, and what happened over
    the simulation steps run so far."""

    __slots__ = (
        "aborted",
        "applied_total",
        "collision_type",
        "collision_with",
        "completed",
        "ego",
        "end_of_road",
        "lane_change",
        "limited_by",
        "red_light",
        "refused",
        "request",
        "signalled_from",
        "started",
        "substeps",
        "teleported",
    )

    def __init__(
        self, ego: EgoState, request: float, lane_change: int, refused: str, started: bool
    ) -> None:
        self.ego = ego
        self.request = request
        self.lane_change = lane_change
        self.refused = refused
        self.started = started
        self.applied_total = 0.0
        self.limited_by = ""
        self.substeps = 0
        self.collision_with = ""
        self.collision_type = ""
        self.red_light = False
        self.end_of_road = False
        self.teleported = False
        self.completed = False
        self.aborted = False
        self.signalled_from: tuple[str, int] | None = None
        """The ego's road and lane when its refused change was kept requested (SUMO backend,
        `_signal_lane_change`); None otherwise."""

    def applied(self, acceleration: float, why: str) -> None:
        """One simulation step ran with `acceleration`; `why` names the rule that limited it
        ("" none): the first step whose value was limited names the decision's."""
        self.applied_total += acceleration
        self.limited_by = self.limited_by or why
        self.substeps += 1

    def outcome(self) -> tuple[AppliedAction, Events]:
        """The decision as applied (mean acceleration over the steps run) and its events."""
        refused = self.refused
        action = AppliedAction(
            requested_acceleration=self.request,
            requested_lane_change=self.lane_change,
            acceleration=self.applied_total / self.substeps,
            lane_change=0 if refused else self.lane_change,
            acceleration_limited_by=self.limited_by,
            lane_change_refused=refused,
        )
        collision_with = self.collision_with
        if not (
            collision_with
            or self.end_of_road
            or self.started
            or self.completed
            or self.aborted
            or refused
            or self.teleported
            or self.red_light
        ):
            return action, QUIET
        events = Events(
            collision=bool(collision_with),
            collision_with=collision_with,
            end_of_road=self.end_of_road,
            lane_change_started=self.started,
            lane_change_completed=self.completed,
            lane_change_refused=bool(refused),
            teleported=self.teleported,
            lane_change_aborted=self.aborted,
            red_light=self.red_light,
            collision_type=self.collision_type if collision_with else "",
        )
        return action, events


class ShareDraw:
    """Which vehicles are egos at a share of the traffic: a seeded sample of those on the road
    at the hand-over, then every vehicle that enters adds the share to a credit and joins when
    the credit reaches 1 (an exact share, spread evenly over the arrivals, starting at a
    seeded phase)."""

    __slots__ = ("_credit", "_random", "entered", "share")

    def __init__(self, share: float, seed: int) -> None:
        self.share = share
        self._random = random.Random(seed)
        self._credit = self._random.random()
        self.entered: list[str] = []
        """Vehicles that entered during the decision being simulated, in their order."""

    def at_hand_over(self, on_road: list[str]) -> list[str]:
        """round(share x vehicles on the road), at least one, chosen at random (in `on_road`'s
        order)."""
        count = max(1, math.floor(self.share * len(on_road) + 0.5))
        chosen = set(self._random.sample(range(len(on_road)), count))
        return [vehicle for i, vehicle in enumerate(on_road) if i in chosen]

    def joining(self) -> list[str]:
        """The vehicles among those that entered since the last call that become egos."""
        joining = []
        for vehicle in self.entered:
            self._credit += self.share
            if self._credit >= 1.0:
                self._credit -= 1.0
                joining.append(vehicle)
        self.entered.clear()
        return joining


NO_COLLISION = ("", "")


def collision_partner(collisions: Any, ego_id: str) -> tuple[str, str]:
    """The vehicle `ego_id` collided with in this simulation step and where (a
    `CollisionType`), or ("", "")."""
    found = NO_COLLISION
    for collision in collisions:
        if collision.collider == ego_id:
            found = (collision.victim, collision_type(collision))
        elif collision.victim == ego_id:
            found = (collision.collider, collision_type(collision))
    return found


def collision_partners(collisions: Any) -> dict[str, tuple[str, str]]:
    """Every vehicle in a collision of this simulation step -> the vehicle it collided with and
    where (the last such collision, as `collision_partner`): two egos that collide end both."""
    partners: dict[str, tuple[str, str]] = {}
    for collision in collisions:
        kind = collision_type(collision)
        partners[collision.collider] = (collision.victim, kind)
        partners[collision.victim] = (collision.collider, kind)
    return partners


def collision_type(collision: Any) -> str:
    """Where a SUMO collision happened: inside a junction (SUMO's type ``junction``, or on a
    junction's internal lane, whose id starts with ":"), else on a lane."""
    inside = collision.type == "junction" or str(collision.lane).startswith(":")
    return CollisionType.JUNCTION if inside else CollisionType.LANE


def multi_observation(
    seq: int,
    time: float,
    reported: Iterable[tuple[str, Observation]],
    truncated: bool,
    last_end: str,
    traffic: Traffic | None,
) -> MultiObservation:
    """The egos that drove into this step (id, observation), in their stable order, as one
    reply: `truncated` at their time limit (every ego is then truncated), terminated with
    `last_end` (the reason of the last end) when none is left, else running."""
    egos = tuple([ego_part(ego_id, obs) for ego_id, obs in reported])
    if truncated:
        return MultiObservation(seq, time, egos, False, True, EndReason.TIME_LIMIT, traffic)
    if last_end:
        return MultiObservation(seq, time, egos, True, False, last_end, traffic)
    return MultiObservation(seq, time, egos, traffic=traffic)
