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
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

import highway_env
import numpy as np
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from protocol.errors import ErrorCode
from protocol.messages import (
    AccelerationLimit,
    AppliedAction,
    Ego,
    Events,
    LeaderTrip,
    Neighbour,
    Neighbours,
    Observation,
    OptionValue,
    ScenarioInfo,
)
from sim_server.backends.base import Backend
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
    end: EndRule = field(init=False)
    """Set at the hand-over: the episode's time runs from there."""

    @property
    def time(self) -> float:
        return self.steps / SIMULATION_FREQUENCY


class HighwayBackend(Backend):
    """highway-env scenes advanced with ``road.act()`` / ``road.step(dt)``; see the module doc."""

    name = "highway"

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
    ) -> _Episode:
        """The road and its vehicles, placed by highway-env's ``create_random``."""
        network = RoadNetwork.straight_road_network(
            scenario.lanes, length=scenario.length, speed_limit=scenario.speed_limit
        )
        road = Road(network=network, np_random=np.random.default_rng(seed), record_history=False)
        spacing = 1.0 / scene.vehicles_density
        ids: dict[Any, str] = {}
        ego = None
        for index in range(scene.vehicles_count + 1):
            vehicle = IDMVehicle.create_random(road, spacing=spacing)
            vehicle.randomize_behavior()
            road.vehicles.append(vehicle)
            if index == scene.vehicles_behind:
                ego, ids[vehicle] = vehicle, EGO_ID
            else:
                ids[vehicle] = f"h{len(ids) - (ego is not None)}"
        episode = _Episode(
            scenario=scenario,
            road=road,
            ego=ego,
            options=options,
            substeps=substeps,
            ids=ids,
            spawn_front={},
        )
        for vehicle in list(road.vehicles):
            front = self._front(episode, vehicle)
            if front >= scenario.length:  # placed beyond the end: never on the road
                if vehicle is ego:
                    raise BackendError(
                        ErrorCode.INVALID_OPTION,
                        "vehicles_behind and vehicles_density place the ego beyond the end of "
                        "the road; fewer vehicles behind it or a higher density",
                    )
                road.vehicles.remove(vehicle)
            episode.spawn_front[vehicle] = front
        return episode

    def _warm_up(self, episode: _Episode) -> None:
        """highway-env's human model drives the ego for ``warmup`` seconds."""
        warmup = episode.options.warmup
        for _ in range(math.ceil(warmup * SIMULATION_FREQUENCY - 1e-9)):
            self._advance(episode)
            if episode.ego.crashed:
                raise BackendError(
                    ErrorCode.INSERTION_FAILED,
                    "the ego crashed during the warm-up (driven by highway-env); try another seed",
                )
        if self._front(episode, episode.ego) >= episode.scenario.length:
            raise BackendError(
                ErrorCode.INVALID_OPTION,
                f"warmup {warmup} s: the ego reached the end of the road before the "
                "client took over",
            )

    @staticmethod
    def _hand_over(episode: _Episode) -> None:
        """Replace the ego's human model by the client's control, in the same list slot."""
        human = episode.ego
        ego = _ClientVehicle.create_from(human)
        ego.target_lane_index = human.lane_index  # a lane change the human began is not ours
        ego.target_speed = episode.scenario.speed_limit  # for the IDM safety check only
        ego.action = dict(human.action)
        vehicles = episode.road.vehicles
        vehicles[vehicles.index(human)] = ego
        episode.ids[ego] = episode.ids.pop(human)
        episode.spawn_front[ego] = episode.spawn_front.pop(human)
        episode.ego = ego

    # ----------------------------------------------------------------------- step

    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        episode = self._episode
        if episode is None or episode.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        refused = self._lane_change_refusal(episode, lane_change) if lane_change else ""
        started = bool(lane_change) and not refused
        if started:
            _from, _to, index = episode.ego.lane_index
            target = index - lane_change  # protocol +1 (left) is highway-env index - 1
            episode.ego.target_lane_index = (_from, _to, target)
            episode.lane_change = LaneChangeUnderWay(target, lane_change, episode.time)
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
                episode.collided = self._collided_with(episode)
                collision_with = episode.ids.get(episode.collided, "unknown")
                break
            if self._front(episode, ego) >= episode.scenario.length:
                end_of_road = True
                break
            if episode.lane_change is not None:
                completed, aborted = self._lane_change_progress(episode, episode.lane_change)
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
        arrived = [
            v for v in road.vehicles if v is not episode.ego and self._front(episode, v) >= length
        ]
        for vehicle in arrived:
            road.vehicles.remove(vehicle)
            if vehicle is episode.leader:
                episode.leader_arrival = episode.time

    def _lane_change_refusal(self, episode: _Episode, direction: int) -> str:
        lanes = episode.scenario.lanes
        _from, _to, index = episode.ego.lane_index
        return lane_change_refusal(
            direction,
            simulator_drives=episode.options.simulator_drives,
            under_way=episode.lane_change,
            ego_lane=lambda: (lanes - 1 - index, lanes),  # highway-env counts from the left
            gap_ok=lambda towards: self._safe(episode, (_from, _to, index - towards)),
        )

    @staticmethod
    def _safe(episode: _Episode, lane_index: tuple[str, str, int]) -> bool:
        """MOBIL's safety criterion for the ego moving to `lane_index` (both directions)."""
        ego = episode.ego
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
    def _lane_change_progress(episode: _Episode, change: LaneChangeUnderWay) -> tuple[bool, bool]:
        """(completed, aborted) of the lane change under way; either ends it."""
        ego = episode.ego
        target = (*ego.lane_index[:2], change.target)
        if ego.lane_index == target:
            _, lateral = episode.road.network.get_lane(target).local_coordinates(ego.position)
            if abs(lateral) < LANE_CHANGE_TOLERANCE:
                episode.lane_change = None
                return True, False
        if change.expired(episode.time):
            episode.lane_change = None
            return False, True
        return False, False

    @staticmethod
    def _collided_with(episode: _Episode) -> Any:
        """highway-env flags both vehicles of a crash: the nearest crashed one is the other."""
        ego = episode.ego
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
        ego, road, lanes = episode.ego, episode.road, episode.scenario.lanes
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
            slots[f"{name}leader"] = self._neighbour(episode, lane, s, lat, front, ahead=True)
            slots[f"{name}follower"] = self._neighbour(episode, lane, s, lat, rear, ahead=False)
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
                changing_lane=0 if episode.lane_change is None else episode.lane_change.direction,
            ),
            neighbours=Neighbours(**slots),
            events=events,
            action=action,
        )

    def _neighbour(
        self, episode: _Episode, lane: Any, s: float, lat: float, other: Any, ahead: bool
    ) -> Neighbour:
        if other is None:
            return self._absent
        other_s, other_lat = lane.local_coordinates(other.position)
        half_lengths = (other.LENGTH + episode.ego.LENGTH) / 2
        gap = (other_s - s if ahead else s - other_s) - half_lengths
        if gap > self.sensor_range:
            return self._absent
        lateral = lat - other_lat  # highway-env's lateral axis points right
        return Neighbour(True, float(gap), float(lateral), float(other.speed), episode.ids[other])

    # ----------------------------------------------------------------------- lifecycle

    def close(self) -> None:
        self._episode = None
