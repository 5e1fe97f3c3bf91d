"""highway-env (Farama's highway simulator) behind the bridge: the same protocol, another simulator.

`sim-server --backend highway` serves ``cf`` (one lane) and ``cflc`` (three lanes) on a 2 km
straight road at 80 km/h, populated with highway-env's own human drivers (`IDMVehicle`: IDM car
following, MOBIL lane changing). highway-env's gym actions cannot express the protocol's action,
so the scene is built with highway-env's own API, as ``HighwayEnv._create_vehicles`` does, and
advanced with ``road.act()`` and ``road.step(dt)``, the two calls of ``AbstractEnv._simulate``,
at 10 Hz: the SUMO server's 0.1 s and 1.0 s decision intervals are then whole numbers of steps.
The client's ego keeps highway-env's lateral controller (lane keeping and lane changes) and
gets the commanded acceleration. How each part of the protocol maps onto highway-env, and where
it differs from SUMO: docs/backends.md.

Many egos (protocol 1.4, a reset naming ``egos`` > 1, at most `MAX_HIGHWAY_EGOS`): highway-env's
own multi-agent placement (``controlled_vehicles``: each controlled vehicle followed by its share
of the humans), driven as the one ego is, each alone (`_Driven`); ids ``ego.0``, ``ego.1``, ... in
the order of highway-env's ``controlled_vehicles`` (rearmost first). An ego whose drive ends is
reported once and removed from the road. ``egos`` 1 is the one-ego episode under the id ``ego``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import highway_env
import numpy as np
from highway_env.road.road import Road, RoadNetwork
from highway_env.utils import near_split
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from protocol.errors import ErrorCode
from protocol.messages import (
    AccelerationLimit,
    AppliedAction,
    Ego,
    EgoObservation,
    EndReason,
    Events,
    LeaderTrip,
    MultiObservation,
    Neighbour,
    Neighbours,
    Observation,
    OptionValue,
    ScenarioInfo,
)
from sim_server.backends.base import Backend, Commands
from sim_server.backends.options import (
    COMMON_OPTIONS,
    Bounds,
    EpisodeOptions,
    ParsedOptions,
    invalid_option,
)
from sim_server.backends.rules import (
    EndRule,
    LaneChangeUnderWay,
    ended,
    lane_change_refusal,
    limit_acceleration,
)
from sim_server.errors import BackendError

SIMULATION_FREQUENCY = 10
"""Simulation steps per second (highway-env's ``simulation_frequency``)."""
DT = 1.0 / SIMULATION_FREQUENCY
EGO_ID = "ego"
MAX_HIGHWAY_EGOS = 16
"""The most egos of one episode (``controlled_vehicles``); highway-env's cost is O(N²) per step
in the vehicles on the road."""
CEILING_HORIZON = 3600.0
"""Longest extra simulated time (s) spent waiting for the leader-at-entry to arrive."""
LANE_CHANGE_TOLERANCE = 0.1
"""A lane change is complete when the ego is within this lateral distance (m) of the target
lane's centre (highway-env's lateral controller converges exponentially, never exactly)."""
SIMULATOR_DRIVERS = ("simulator", "sumo")
"""Values of ``ego_driver`` that let highway-env's human model drive the ego."""

_HONOURED = (
    "decision_interval",
    "max_episode_time",
    "warmup",
    "stop_speed",
    "stop_gap",
    "stop_patience",
    "report_ceiling",
    "ego_driver",
    "egos",
)
"""The SUMO server's common options this backend honours: the same meaning, except that during
the ``warmup`` highway-env's own human model drives the ego (it is on the road from the start)."""

_REFERENCE_IDM = IDMVehicle(None, np.zeros(2))
"""IDM parameters for safety checks of a vehicle that is not itself an IDM vehicle (the ego)."""


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
        options: dict[str, OptionValue] = {name: COMMON_OPTIONS[name] for name in _HONOURED}
        options.update(warmup=5.0, **SceneOptions().as_options())
        options.update(self.defaults)
        return ScenarioInfo(self.name, self.description, options, DT)


SCENARIOS: dict[str, HighwayScenario] = {
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
    )
}


class _ClientVehicle(ControlledVehicle):  # type: ignore[misc]
    """The client's ego: highway-env's lateral controller, the client's acceleration."""

    command: float = 0.0

    def act(self, action: Any = None) -> None:
        self.follow_road()
        steering = self.steering_control(self.target_lane_index)
        steering = float(np.clip(steering, -self.MAX_STEERING_ANGLE, self.MAX_STEERING_ANGLE))
        Vehicle.act(self, {"steering": steering, "acceleration": self.command})


@dataclass
class _Driven:
    """One ego of a multi-ego episode and its own book-keeping (a one-ego episode keeps its
    ego's in `_Episode`)."""

    id: str
    vehicle: Any
    end: EndRule
    lane_change: LaneChangeUnderWay | None = None
    over: bool = False
    """Its drive has ended (reported once, then off the road)."""


@dataclass
class _Turn:
    """One ego's part of a decision of a multi-ego episode."""

    driven: _Driven
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
    completed: bool = False
    aborted: bool = False
    last: Observation | None = None
    """Observed at the simulation step where its drive ended inside the decision."""

    @property
    def stopped_inside(self) -> bool:
        return bool(self.collision_with) or self.end_of_road

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
class _Episode:
    """The running scene and its book-keeping."""

    scenario: HighwayScenario
    road: Any
    ego: Any
    options: EpisodeOptions
    substeps: int
    ids: dict[Any, str]
    spawn_front: dict[Any, float]
    steps: int = 0
    leader: Any = None
    leader_arrival: float | None = None
    lane_change: LaneChangeUnderWay | None = None
    collided: Any = None
    done: bool = False
    fleet: list[_Driven] = field(default_factory=list)
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


class HighwayBackend(Backend):
    """highway-env scenes advanced with ``road.act()`` / ``road.step(dt)``; see the module doc."""

    name = "highway"
    max_egos = MAX_HIGHWAY_EGOS

    def __init__(self) -> None:
        self._episode: _Episode | None = None
        self._absent = Neighbour(False, self.sensor_range, 0.0, 0.0, "")

    @property
    def version(self) -> str:
        return str(highway_env.__version__)

    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        return tuple(s.info() for s in SCENARIOS.values())

    # ----------------------------------------------------------------------- reset

    def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
        chosen = SCENARIOS.get(scenario)
        if chosen is None:
            raise BackendError(ErrorCode.UNKNOWN_SCENARIO, f"unknown scenario {scenario[:64]!r}")
        episode_options = EpisodeOptions.parse(options, SIMULATOR_DRIVERS)
        scene = SceneOptions.parse(options)
        substeps = episode_options.steps_per_decision(DT)
        self._episode = None
        episode = self._build(chosen, seed, episode_options, scene, substeps)
        self._warm_up(episode)
        if not episode_options.simulator_drives:
            self._hand_over(episode)
        episode.end = EndRule(episode_options, entry_time=episode.time)
        episode.leader, _ = episode.road.neighbour_vehicles(episode.ego, episode.ego.lane_index)
        self._episode = episode
        return self._observe(episode, 0, Events(), AppliedAction(0.0, 0, 0.0, 0))

    def _build(
        self,
        scenario: HighwayScenario,
        seed: int,
        options: EpisodeOptions,
        scene: SceneOptions,
        substeps: int,
        names: tuple[str, ...] = (EGO_ID,),
    ) -> _Episode:
        """The road and its vehicles, placed by highway-env's ``create_random``: `vehicles_behind`
        humans, then each ego of `names` followed by its share of the other humans (highway-env's
        ``near_split``, as its ``_create_vehicles`` places ``controlled_vehicles``)."""
        network = RoadNetwork.straight_road_network(
            scenario.lanes, length=scenario.length, speed_limit=scenario.speed_limit
        )
        road = Road(network=network, np_random=np.random.default_rng(seed), record_history=False)
        spacing = 1.0 / scene.vehicles_density
        shares = near_split(scene.vehicles_count - scene.vehicles_behind, num_bins=len(names))
        plan: list[str | None] = [None] * scene.vehicles_behind
        for name, share in zip(names, shares, strict=True):
            plan += [name, *[None] * int(share)]
        ids: dict[Any, str] = {}
        egos: dict[Any, str] = {}
        for role in plan:
            vehicle = IDMVehicle.create_random(road, spacing=spacing)
            vehicle.randomize_behavior()
            road.vehicles.append(vehicle)
            if role is None:
                ids[vehicle] = f"h{len(ids) - len(egos)}"
            else:
                ids[vehicle] = egos[vehicle] = role
        fleet: list[_Driven] = [] if names == (EGO_ID,) else [
            _Driven(name, vehicle, EndRule(options, 0.0)) for vehicle, name in egos.items()
        ]  # fmt: skip
        episode = _Episode(
            scenario=scenario,
            road=road,
            ego=None if fleet else next(iter(egos)),
            options=options,
            substeps=substeps,
            ids=ids,
            spawn_front={},
            fleet=fleet,
        )
        for vehicle in list(road.vehicles):
            front = self._front(episode, vehicle)
            if front >= scenario.length:  # placed beyond the end: never on the road
                if vehicle in egos:
                    what = "the ego" if not fleet else egos[vehicle]
                    raise BackendError(
                        ErrorCode.INVALID_OPTION,
                        f"vehicles_behind and vehicles_density place {what} beyond the end of "
                        "the road; fewer vehicles behind it or a higher density"
                        + ("" if not fleet else ", or fewer egos"),
                    )
                road.vehicles.remove(vehicle)
            episode.spawn_front[vehicle] = front
        return episode

    def _warm_up(self, episode: _Episode) -> None:
        """highway-env's human model drives the ego for ``warmup`` seconds."""
        warmup = episode.options.warmup
        names = {d.vehicle: d.id for d in episode.fleet}
        for _ in range(math.ceil(warmup * SIMULATION_FREQUENCY - 1e-9)):
            self._advance(episode)
            for ego in episode.egos():
                if ego.crashed:
                    what = names.get(ego, "the ego")
                    raise BackendError(
                        ErrorCode.INSERTION_FAILED,
                        f"{what} crashed during the warm-up (driven by highway-env); try "
                        "another seed",
                    )
        for ego in episode.egos():
            if self._front(episode, ego) >= episode.scenario.length:
                what = names.get(ego, "the ego")
                raise BackendError(
                    ErrorCode.INVALID_OPTION,
                    f"warmup {warmup} s: {what} reached the end of the road before the "
                    "client took over",
                )

    @classmethod
    def _hand_over(cls, episode: _Episode) -> None:
        """Replace the ego's human model by the client's control, in the same list slot."""
        if not episode.fleet:
            episode.ego = cls._take_over(episode, episode.ego)
        for driven in episode.fleet:
            driven.vehicle = cls._take_over(episode, driven.vehicle)

    @staticmethod
    def _take_over(episode: _Episode, human: Any) -> Any:
        """The client's vehicle in `human`'s place (list slot, id, spawn position)."""
        ego = _ClientVehicle.create_from(human)
        ego.target_lane_index = human.lane_index  # a lane change the human began is not ours
        ego.target_speed = episode.scenario.speed_limit  # for the IDM safety check only
        ego.action = dict(human.action)
        vehicles = episode.road.vehicles
        vehicles[vehicles.index(human)] = ego
        episode.ids[ego] = episode.ids.pop(human)
        episode.spawn_front[ego] = episode.spawn_front.pop(human)
        return ego

    # ----------------------------------------------------------------------- step

    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        episode = self._episode
        if episode is None or episode.done or episode.fleet:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        refused = (
            self._lane_change_refusal(episode, episode.ego, episode.lane_change, lane_change)
            if lane_change
            else ""
        )
        started = bool(lane_change) and not refused
        if started:
            episode.lane_change = self._start_lane_change(episode, episode.ego, lane_change)
        action, events = self._drive(episode, acceleration, lane_change, refused, started)
        obs = self._observe(episode, seq, events, action)
        reason = episode.end.check(obs)
        if reason is None:
            return obs
        episode.done = True
        obs = ended(obs, reason)
        if episode.options.report_ceiling:
            obs = replace(obs, ceiling=self._leader_trip(episode))
        return obs

    def _drive(
        self, episode: _Episode, request: float, lane_change: int, refused: str, started: bool
    ) -> tuple[AppliedAction, Events]:
        """Run the decision's simulation steps, the request limited anew on each (bounds, speed
        limit, standstill); stop early at a crash or the end of the road."""
        ego, drives = episode.ego, episode.options.simulator_drives
        low, high = self.action_schema.acceleration_min, self.action_schema.acceleration_max
        limit = episode.scenario.speed_limit
        applied_total, limited_by = 0.0, ""
        collision_with, end_of_road, completed, aborted = "", False, False, False
        done = 0
        for _ in range(episode.substeps):
            why: str = AccelerationLimit.SIMULATOR
            if not drives:
                ego.command, why = limit_acceleration(
                    request, float(ego.speed), limit, low, high, DT
                )
            self._advance(episode)
            if not drives and ego.speed < 0.0:
                ego.speed = 0.0  # rounding of -v/dt * dt; the protocol's speed is >= 0
            applied_total += float(ego.action["acceleration"])
            limited_by = limited_by or why
            done += 1
            if ego.crashed:
                episode.collided = self._collided_with(episode, ego)
                collision_with = episode.ids.get(episode.collided, "unknown")
                break
            if self._front(episode, ego) >= episode.scenario.length:
                end_of_road = True
                break
            if episode.lane_change is not None:
                completed, aborted = self._lane_change_progress(episode, ego, episode.lane_change)
                if completed or aborted:
                    episode.lane_change = None
        action = AppliedAction(
            requested_acceleration=request,
            requested_lane_change=lane_change,
            acceleration=applied_total / done,
            lane_change=0 if refused else lane_change,
            acceleration_limited_by=limited_by,
            lane_change_refused=refused,
        )
        events = Events(
            collision=bool(collision_with),
            collision_with=collision_with,
            end_of_road=end_of_road,
            lane_change_started=started,
            lane_change_completed=completed,
            lane_change_refused=bool(refused),
            lane_change_aborted=aborted,
        )
        return action, events

    def _advance(self, episode: _Episode) -> None:
        """One simulation step: highway-env's ``road.act()`` and ``road.step(dt)``, arrivals."""
        road = episode.road
        road.act()
        road.step(DT)
        episode.steps += 1
        length = episode.scenario.length
        egos = episode.egos()
        arrived = [
            v
            for v in road.vehicles
            if all(v is not ego for ego in egos) and self._front(episode, v) >= length
        ]
        for vehicle in arrived:
            road.vehicles.remove(vehicle)
            if vehicle is episode.leader:
                episode.leader_arrival = episode.time

    def _lane_change_refusal(
        self, episode: _Episode, ego: Any, under_way: LaneChangeUnderWay | None, direction: int
    ) -> str:
        lanes = episode.scenario.lanes
        _from, _to, index = ego.lane_index
        return lane_change_refusal(
            direction,
            simulator_drives=episode.options.simulator_drives,
            under_way=under_way,
            ego_lane=lambda: (lanes - 1 - index, lanes),  # highway-env counts from the left
            gap_ok=lambda towards: self._safe(episode, ego, (_from, _to, index - towards)),
        )

    @staticmethod
    def _start_lane_change(episode: _Episode, ego: Any, direction: int) -> LaneChangeUnderWay:
        """Steer `ego` one lane towards `direction` (not refused)."""
        _from, _to, index = ego.lane_index
        target = index - direction  # protocol +1 (left) is highway-env index - 1
        ego.target_lane_index = (_from, _to, target)
        return LaneChangeUnderWay(target, direction, episode.time)

    @staticmethod
    def _safe(episode: _Episode, ego: Any, lane_index: tuple[str, str, int]) -> bool:
        """MOBIL's safety criterion for `ego` moving to `lane_index` (both directions)."""
        front, rear = episode.road.neighbour_vehicles(ego, lane_index)
        limit = IDMVehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED
        if rear is not None:
            model = rear if isinstance(rear, IDMVehicle) else _REFERENCE_IDM
            if model.acceleration(ego_vehicle=rear, front_vehicle=ego) < -limit:
                return False
        return (
            front is None
            or _REFERENCE_IDM.acceleration(ego_vehicle=ego, front_vehicle=front) >= -limit
        )

    @staticmethod
    def _lane_change_progress(
        episode: _Episode, ego: Any, change: LaneChangeUnderWay
    ) -> tuple[bool, bool]:
        """(completed, aborted) of `ego`'s lane change under way; either ends it."""
        target = (*ego.lane_index[:2], change.target)
        if ego.lane_index == target:
            _, lateral = episode.road.network.get_lane(target).local_coordinates(ego.position)
            if abs(lateral) < LANE_CHANGE_TOLERANCE:
                return True, False
        if change.expired(episode.time):
            return False, True
        return False, False

    @staticmethod
    def _collided_with(episode: _Episode, ego: Any) -> Any:
        """highway-env flags both vehicles of a crash: the nearest crashed one is the other."""
        crashed = [v for v in episode.road.vehicles if v is not ego and v.crashed]
        if not crashed:
            return None
        return min(crashed, key=lambda v: float(np.linalg.norm(v.position - ego.position)))

    def _leader_trip(self, episode: _Episode) -> LeaderTrip | None:
        """Run on without the ego until the leader-at-entry arrives; its (virtual) trip."""
        leader = episode.leader
        if leader is None:
            return None
        road = episode.road
        if episode.leader_arrival is None:
            if episode.ego in road.vehicles:
                road.vehicles.remove(episode.ego)
            if episode.collided is not None:  # SUMO's collision action "warn": it drives on
                episode.collided.crashed, episode.collided.impact = False, None
            # IDM looks ahead only: on one lane the vehicles behind cannot influence the leader.
            # On more lanes one could overtake and cut in; dropping them is an approximation
            # (docs/backends.md, "Ceiling")
            mine = self._front(episode, leader)
            road.vehicles = [v for v in road.vehicles if self._front(episode, v) >= mine]
            end = episode.steps + round(CEILING_HORIZON * SIMULATION_FREQUENCY)
            while episode.leader_arrival is None and episode.steps < end:
                if leader.crashed:
                    break  # crashed with a human: highway-env stops it for good, it never arrives
                self._advance(episode)
        arrival = episode.leader_arrival
        name = episode.ids[leader]
        if arrival is None:
            return LeaderTrip(name, 0.0, None, None)
        length = episode.scenario.length
        average = (length - episode.spawn_front[leader]) / arrival
        return LeaderTrip(name, arrival - length / average, arrival, average)

    # ----------------------------------------------------------------------- observation

    @staticmethod
    def _front(episode: _Episode, vehicle: Any) -> float:
        """Distance of a vehicle's front from the start of the road (lanes start at x = 0)."""
        lane = episode.road.network.get_lane(vehicle.lane_index)
        longitudinal, _ = lane.local_coordinates(vehicle.position)
        return float(longitudinal + vehicle.LENGTH / 2)

    def _observe(
        self, episode: _Episode, seq: int, events: Events, action: AppliedAction
    ) -> Observation:
        return self._observe_ego(episode, episode.ego, episode.lane_change, seq, events, action)

    def _observe_ego(
        self,
        episode: _Episode,
        ego: Any,
        change: LaneChangeUnderWay | None,
        seq: int,
        events: Events,
        action: AppliedAction,
    ) -> Observation:
        """`ego`'s observation: its own state and its six neighbours (other egos included)."""
        road, lanes = episode.road, episode.scenario.lanes
        _from, _to, index = ego.lane_index
        lane = road.network.get_lane(ego.lane_index)
        s, lat = lane.local_coordinates(ego.position)
        slots: dict[str, Neighbour] = {}
        for name, offset in (("left_", -1), ("", 0), ("right_", 1)):
            other = index + offset
            if not 0 <= other < lanes:
                slots[f"{name}leader"] = slots[f"{name}follower"] = self._absent
                continue
            front, rear = road.neighbour_vehicles(ego, (_from, _to, other))
            slots[f"{name}leader"] = self._neighbour(episode, ego, lane, s, lat, front, True)
            slots[f"{name}follower"] = self._neighbour(episode, ego, lane, s, lat, rear, False)
        return Observation(
            seq=seq,
            time=episode.time,
            ego=Ego(
                speed=float(ego.speed),
                acceleration=float(ego.action["acceleration"]),
                lane=lanes - 1 - int(index),
                lane_count=lanes,
                position=min(float(s + ego.LENGTH / 2), episode.scenario.length),
                speed_limit=float(lane.speed_limit),
                changing_lane=0 if change is None else change.direction,
            ),
            neighbours=Neighbours(**slots),
            events=events,
            action=action,
        )

    def _neighbour(
        self,
        episode: _Episode,
        ego: Any,
        lane: Any,
        s: float,
        lat: float,
        other: Any,
        ahead: bool,
    ) -> Neighbour:
        if other is None:
            return self._absent
        other_s, other_lat = lane.local_coordinates(other.position)
        half_lengths = (other.LENGTH + ego.LENGTH) / 2
        gap = (other_s - s if ahead else s - other_s) - half_lengths
        if gap > self.sensor_range:
            return self._absent
        lateral = lat - other_lat  # highway-env's lateral axis points right
        return Neighbour(True, float(gap), float(lateral), float(other.speed), episode.ids[other])

    # ----------------------------------------------------------------------- many egos

    def reset_many(
        self, scenario: str, seed: int, options: dict[str, OptionValue], egos: int
    ) -> MultiObservation:
        """``egos`` 1: the one-ego episode under the id ``ego`` (without the ceiling's run-on: a
        multi observation has no ceiling); more: ``ego.0``... placed as highway-env places its
        ``controlled_vehicles`` (`_build`), handed over together after the warm-up."""
        if egos == 1 or egos > self.max_egos:
            quiet = {**options, "report_ceiling": False}
            return super().reset_many(scenario, seed, quiet, egos)  # or its refusal
        chosen = SCENARIOS.get(scenario)
        if chosen is None:
            raise BackendError(ErrorCode.UNKNOWN_SCENARIO, f"unknown scenario {scenario[:64]!r}")
        episode_options = EpisodeOptions.parse(options, SIMULATOR_DRIVERS)
        scene = SceneOptions.parse(options)
        substeps = episode_options.steps_per_decision(DT)
        names = tuple(f"ego.{k}" for k in range(egos))
        self._episode = None
        episode = self._build(chosen, seed, episode_options, scene, substeps, names)
        self._warm_up(episode)
        if not episode_options.simulator_drives:
            self._hand_over(episode)
        episode.end = EndRule(episode_options, entry_time=episode.time)
        for driven in episode.fleet:
            driven.end = EndRule(episode_options, entry_time=episode.time)
        self._episode = episode
        still = AppliedAction(0.0, 0, 0.0, 0)
        firsts = [
            self._observe_ego(episode, d.vehicle, None, 0, Events(), still) for d in episode.fleet
        ]
        mine = tuple(_mine(d.id, obs) for d, obs in zip(episode.fleet, firsts, strict=True))
        return MultiObservation(0, episode.time, mine)

    def step_many(self, seq: int, commands: Commands) -> MultiObservation:
        episode = self._episode
        if episode is not None and not episode.fleet:
            return super().step_many(seq, commands)  # a one-ego episode (egos 1)
        if episode is None or episode.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        turns = [self._turn(episode, d, *commands[d.id]) for d in episode.fleet if not d.over]
        self._drive_many(episode, seq, turns)
        ends: list[tuple[int, EndReason]] = []
        egos: list[EgoObservation] = []
        for turn in turns:
            action, events = turn.result()
            driven = turn.driven
            obs = turn.last or self._observe_ego(
                episode, driven.vehicle, driven.lane_change, seq, events, action
            )
            reason = driven.end.check(obs)
            if reason is not None:
                obs = ended(obs, reason)
                driven.over = True
                ends.append((turn.steps, reason))  # in time, then in the egos' order
                if driven.vehicle in episode.road.vehicles:
                    episode.road.vehicles.remove(driven.vehicle)
            egos.append(_mine(driven.id, obs))
        ends.sort(key=lambda end: end[0])  # stable: within a step, the egos' order
        return self._frame(episode, seq, tuple(egos), ends[-1][1] if ends else "")

    def _turn(self, episode: _Episode, driven: _Driven, request: float, lane_change: int) -> _Turn:
        """`driven`'s command checked and its lane change begun (or refused)."""
        refused = (
            self._lane_change_refusal(episode, driven.vehicle, driven.lane_change, lane_change)
            if lane_change
            else ""
        )
        started = bool(lane_change) and not refused
        if started:
            driven.lane_change = self._start_lane_change(episode, driven.vehicle, lane_change)
        return _Turn(driven, request, lane_change, refused, started)

    def _drive_many(self, episode: _Episode, seq: int, turns: list[_Turn]) -> None:
        """Run the decision's simulation steps for every ego at once, each request limited anew
        on each step; an ego that crashes or reaches the end of the road is observed at that step
        and taken off the road, the others drive on."""
        drives = episode.options.simulator_drives
        low, high = self.action_schema.acceleration_min, self.action_schema.acceleration_max
        limit = episode.scenario.speed_limit
        for _ in range(episode.substeps):
            active = [t for t in turns if not t.stopped_inside]
            if not active:
                break
            for turn in active:
                ego = turn.driven.vehicle
                turn.why = AccelerationLimit.SIMULATOR
                if not drives:
                    ego.command, turn.why = limit_acceleration(
                        turn.request, float(ego.speed), limit, low, high, DT
                    )
            self._advance(episode)
            for turn in active:
                ego = turn.driven.vehicle
                if not drives and ego.speed < 0.0:
                    ego.speed = 0.0  # as for one ego
                turn.applied_total += float(ego.action["acceleration"])
                turn.limited_by = turn.limited_by or turn.why
                turn.steps += 1
                self._judge_step(episode, turn)
            stopped = [t for t in active if t.stopped_inside]
            for turn in stopped:  # observed before any leaves: two egos that collide see each other
                action, events = turn.result()
                driven = turn.driven
                turn.last = self._observe_ego(
                    episode, driven.vehicle, driven.lane_change, seq, events, action
                )
            for turn in stopped:
                episode.road.vehicles.remove(turn.driven.vehicle)

    def _judge_step(self, episode: _Episode, turn: _Turn) -> None:
        """After a simulation step: `turn`'s crash, end of road or lane-change progress."""
        driven = turn.driven
        ego = driven.vehicle
        if ego.crashed:
            turn.collision_with = episode.ids.get(self._collided_with(episode, ego), "unknown")
        elif self._front(episode, ego) >= episode.scenario.length:
            turn.end_of_road = True
        elif driven.lane_change is not None:
            completed, aborted = self._lane_change_progress(episode, ego, driven.lane_change)
            turn.completed, turn.aborted = turn.completed or completed, turn.aborted or aborted
            if completed or aborted:
                driven.lane_change = None

    @staticmethod
    def _frame(
        episode: _Episode, seq: int, egos: tuple[EgoObservation, ...], last_end: str
    ) -> MultiObservation:
        """The decision's frame: truncated at the time limit, terminated once no ego is left
        (with `last_end`, the reason of the last end)."""
        truncated = any(e.truncated for e in egos)
        terminated = not truncated and all(d.over for d in episode.fleet)
        reason = ""
        if truncated:
            reason = EndReason.TIME_LIMIT
        elif terminated:
            reason = last_end
        episode.done = truncated or terminated
        return MultiObservation(seq, episode.time, egos, terminated, truncated, reason)

    # ----------------------------------------------------------------------- lifecycle

    def close(self) -> None:
        self._episode = None


def _mine(ego_id: str, obs: Observation) -> EgoObservation:
    """One ego's part of a frame: `obs` without the clock."""
    return EgoObservation(
        ego_id, obs.ego, obs.neighbours, obs.events, obs.action,
        obs.terminated, obs.truncated, obs.reason,
    )  # fmt: skip
