"""highway-env (Farama's highway simulator) behind the bridge: the same protocol, another simulator.

`sim-server --backend highway` serves scenarios ``cf`` (one lane) and ``cflc`` (three lanes) on a
2 km straight road at 80 km/h, populated with highway-env's own human drivers
(`highway_env.vehicle.behavior.IDMVehicle`: IDM car following, MOBIL lane changing, a randomised
IDM exponent per vehicle). Details and measurements: docs/backends.md.

How highway-env is driven (and why not through ``gym.Env.step``):

* highway-env's gym actions cannot express the protocol's action: ``ContinuousAction`` sets an
  acceleration but steers by hand (no lane keeping, no lane change), ``DiscreteMetaAction`` changes
  lanes but only tracks a few target speeds. So this backend builds the scene with highway-env's
  own API (``RoadNetwork.straight_road_network``, ``IDMVehicle.create_random``, as
  ``HighwayEnv._create_vehicles`` does) and advances it with ``road.act()`` and
  ``road.step(dt)``, the two calls ``AbstractEnv._simulate`` makes, at a simulation frequency of
  10 Hz (highway-env's default is 15 Hz; 10 Hz makes the 0.1 s and 1.0 s decision intervals of
  the SUMO server exact multiples of the step).
* The client's ego is a `ControlledVehicle` whose ``act()`` keeps highway-env's lateral
  controller (``steering_control(target_lane_index)``: lane keeping, and lane changes by moving
  ``target_lane_index`` one lane over) but replaces its longitudinal speed controller by the
  commanded acceleration, clipped to the action schema and to ``[0, speed limit]`` on every
  simulation step of the decision. highway-env integrates ``speed += acceleration * dt``, so the
  commanded acceleration is realised exactly.
* Lane indices: highway-env numbers lanes from the left (``LANE_LEFT`` is index - 1); the
  protocol numbers them from the right. Protocol lane = lanes - 1 - highway-env lane; lateral
  offsets are negated likewise (highway-env's lateral axis points to the right of the heading).
* A lane change (~1.8 s; SUMO's takes 2 s) is refused with ``no_lane`` beyond the road's edge,
  ``in_progress`` while the previous one has not converged (within 0.1 m of the target lane's
  centre: ``lane_change_completed``), and
  ``gap_too_small`` by highway-env's own safety rule, MOBIL's braking criterion: the new
  follower, or the ego itself behind its new leader, would need to brake harder than
  ``IDMVehicle.LANE_CHANGE_MAX_BRAKING_IMPOSED`` (2 m/s^2) by IDM.
* Collisions are highway-env's ``crashed`` flag: set when the two bodies' rectangles intersect
  (a real overlap). They are checked on every simulation step, before the end of the road;
  ``collision_with`` is the nearest other crashed vehicle (highway-env flags both).
* Scene: ``vehicles_behind`` humans are placed first, then the ego, then the rest of
  ``vehicles_count`` ahead of it, each ``create_random`` spacing (``1 / vehicles_density``) ahead of
  the previous one, at 70-80 % of the speed limit (their IDM target speed). Vehicles whose front
  passes the end of the road leave it (SUMO's arrival). There is no inflow: the road empties
  ahead of the platoon.
* ``warmup``: the ego is on the road from the start, driven by highway-env's own human model
  (an `IDMVehicle` like the others) for ``warmup`` seconds while the traffic settles from its
  artificial initial spacing; then the client takes over (SUMO instead inserts the ego at the
  start of the road after the warm-up). ``ego_driver = "simulator"`` (alias ``"sumo"``, so that
  clients written for the SUMO server, e.g. ``agent-client calibrate-idm``, run unchanged) keeps
  highway-env's human model driving the ego for the whole episode.
* Ceiling (LeaderTrip): the vehicle directly ahead of the ego at hand-over. highway-env spawns
  vehicles on the road, not at its start, so its departure is virtual:
  ``depart_time = arrival_time - road length / average_speed`` with ``average_speed`` its mean
  speed from its spawn (t = 0) to its arrival. The bridge's formula then gives exactly the ego's
  speed when arriving together with it. As in SUMO, after the ego's last step the simulation
  runs on without the ego until that vehicle arrives (at most an hour of simulated time). The
  vehicles behind it are dropped first: with IDM they cannot influence it on one lane (exact);
  on more lanes this is an approximation (one could overtake and cut in). highway-env stops a
  crashed vehicle for good, so the vehicle the ego hit is released first (SUMO's collision
  action "warn" lets both drive on); a leader crashed with a human never arrives.
* Determinism: the seed seeds the ``numpy.random.Generator`` given to ``Road`` as its
  ``np_random``, the only source of randomness highway-env uses for this scene.
* Not honoured, hence not offered: ``insertion_timeout`` (the ego never waits to enter) and
  SUMO's route-file options (``flow``, ``speed_factor_*``, ``sigma``), replaced by highway-env's
  ``vehicles_count`` and ``vehicles_density``. ``events.teleported`` is always false.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import highway_env
import numpy as np
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle
from highway_env.vehicle.kinematics import Vehicle

from protocol.errors import ErrorCode
from protocol.messages import (
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
from sim_server.backend import Backend, BackendError, LaneChange
from sim_server.scenarios import COMMON_OPTIONS, check_options

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
"""The SUMO server's common options this backend honours (same meaning, see the docstring)."""

_REFERENCE_IDM = IDMVehicle(None, np.zeros(2))
"""IDM parameters for safety checks of a vehicle that is not itself an IDM vehicle (the ego)."""


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
        options.update(warmup=5.0, vehicles_count=12, vehicles_behind=2, vehicles_density=0.6)
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
    options: dict[str, OptionValue]
    substeps: int
    ids: dict[Any, str]
    spawn_front: dict[Any, float]
    steps: int = 0
    entry_time: float = 0.0
    simulator_drives: bool = False
    leader: Any = None
    leader_arrival: float | None = None
    lane_change: LaneChange | None = None
    stopped_since: float | None = None
    collided: Any = None
    done: bool = False

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
        substeps = _check_options(options)
        self._episode = None
        episode = self._build(chosen, seed, options, substeps)
        warmup_steps = math.ceil(float(options["warmup"]) * SIMULATION_FREQUENCY - 1e-9)  # type: ignore[arg-type]
        for _ in range(warmup_steps):
            self._advance(episode)
            if episode.ego.crashed:
                raise BackendError(
                    ErrorCode.INSERTION_FAILED,
                    "the ego crashed during the warm-up (driven by highway-env); try another seed",
                )
        if self._front(episode, episode.ego) >= chosen.length:
            raise BackendError(
                ErrorCode.INVALID_OPTION,
                f"warmup {options['warmup']} s: the ego reached the end of the road before the "
                "client took over",
            )
        if not episode.simulator_drives:
            self._hand_over(episode)
        episode.entry_time = episode.time
        episode.leader, _ = episode.road.neighbour_vehicles(episode.ego, episode.ego.lane_index)
        self._episode = episode
        return self._observe(episode, 0, Events(), AppliedAction(0.0, 0, 0.0, 0))

    def _build(
        self, scenario: HighwayScenario, seed: int, options: dict[str, OptionValue], substeps: int
    ) -> _Episode:
        """The road and its vehicles, placed by highway-env's ``create_random``."""
        network = RoadNetwork.straight_road_network(
            scenario.lanes, length=scenario.length, speed_limit=scenario.speed_limit
        )
        road = Road(network=network, np_random=np.random.default_rng(seed), record_history=False)
        spacing = 1.0 / float(options["vehicles_density"])  # type: ignore[arg-type]
        count = int(options["vehicles_count"])  # type: ignore[arg-type]
        behind = min(int(options["vehicles_behind"]), count)  # type: ignore[arg-type]
        ids: dict[Any, str] = {}
        ego = None
        for index in range(count + 1):
            vehicle = IDMVehicle.create_random(road, spacing=spacing)
            vehicle.randomize_behavior()
            road.vehicles.append(vehicle)
            if index == behind:
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
            simulator_drives=options["ego_driver"] in SIMULATOR_DRIVERS,
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
        ego = episode.ego
        if episode.simulator_drives:
            refused = "simulator_drives" if lane_change else ""
        else:
            refused = self._lane_change_refusal(episode, lane_change) if lane_change else ""
        started = bool(lane_change) and not refused
        if started:
            _from, _to, index = ego.lane_index
            target = index - lane_change  # protocol +1 (left) is highway-env index - 1
            ego.target_lane_index = (_from, _to, target)
            episode.lane_change = LaneChange(target, lane_change, episode.time)
        low, high = self.action_schema.acceleration_min, self.action_schema.acceleration_max
        limit = episode.scenario.speed_limit
        applied_total, limited_by = 0.0, ""
        collision_with, end_of_road, completed, aborted = "", False, False, False
        done = 0
        for _ in range(episode.substeps):
            if episode.simulator_drives:
                why = "simulator"
            else:
                ego.command, why = _limit_acceleration(
                    acceleration, float(ego.speed), limit, low, high, DT
                )
            self._advance(episode)
            if not episode.simulator_drives and ego.speed < 0.0:
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
                if self._lane_change_done(episode):
                    episode.lane_change, completed = None, True
                elif episode.lane_change.expired(episode.time):
                    episode.lane_change, aborted = None, True
        action = AppliedAction(
            requested_acceleration=acceleration,
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
        obs = self._observe(episode, seq, events, action)
        reason = self._termination(episode, obs)
        if not reason:
            return obs
        truncated = reason == "time_limit"
        obs = replace(obs, terminated=not truncated, truncated=truncated, reason=reason)
        episode.done = True
        if episode.options["report_ceiling"]:
            obs = replace(obs, ceiling=self._leader_trip(episode))
        return obs

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
        if episode.lane_change is not None:
            return "in_progress"
        _from, _to, index = episode.ego.lane_index
        target = index - direction
        if not 0 <= target < episode.scenario.lanes:
            return "no_lane"
        if not self._safe(episode, (_from, _to, target)):
            return "gap_too_small"
        return ""

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
    def _lane_change_done(episode: _Episode) -> bool:
        ego, change = episode.ego, episode.lane_change
        assert change is not None
        target = (*ego.lane_index[:2], change.target)
        if ego.lane_index != target:
            return False
        _, lateral = episode.road.network.get_lane(target).local_coordinates(ego.position)
        return bool(abs(lateral) < LANE_CHANGE_TOLERANCE)

    @staticmethod
    def _collided_with(episode: _Episode) -> Any:
        """highway-env flags both vehicles of a crash: the nearest crashed one is the other."""
        ego = episode.ego
        crashed = [v for v in episode.road.vehicles if v is not ego and v.crashed]
        if not crashed:
            return None
        return min(crashed, key=lambda v: float(np.linalg.norm(v.position - ego.position)))

    def _termination(self, episode: _Episode, obs: Observation) -> str:
        options = episode.options
        if obs.events.collision:
            return "collision"
        if obs.events.end_of_road:
            return "end_of_road"
        leader = obs.neighbours.leader
        far = not leader.present or leader.gap > float(options["stop_gap"])  # type: ignore[arg-type]
        slower = not leader.present or obs.ego.speed < leader.speed
        if obs.ego.speed < float(options["stop_speed"]) and far and slower:  # type: ignore[arg-type]
            if episode.stopped_since is None:
                episode.stopped_since = obs.time
            if obs.time - episode.stopped_since >= float(options["stop_patience"]) - 1e-9:  # type: ignore[arg-type]
                return "stopped"
        else:
            episode.stopped_since = None
        if obs.time - episode.entry_time >= float(options["max_episode_time"]) - 1e-9:  # type: ignore[arg-type]
            return "time_limit"
        return ""

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
            # (docs/backends.md: same arrival times on the seeds measured, 40 % less time).
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


def _check_options(options: dict[str, OptionValue]) -> int:
    """Range checks; returns the simulation steps per decision."""
    check_options({k: v for k, v in options.items() if k != "ego_driver"})
    driver = options["ego_driver"]
    if driver != "agent" and driver not in SIMULATOR_DRIVERS:
        raise BackendError(
            ErrorCode.INVALID_OPTION,
            "option ego_driver must be agent or simulator (sumo is accepted as an alias)",
        )
    count, behind = int(options["vehicles_count"]), int(options["vehicles_behind"])  # type: ignore[arg-type]
    if not 0 <= count <= 200:
        raise BackendError(ErrorCode.INVALID_OPTION, "option vehicles_count must be in 0..200")
    if not 0 <= behind <= count:
        raise BackendError(
            ErrorCode.INVALID_OPTION, "option vehicles_behind must be in 0..vehicles_count"
        )
    density = float(options["vehicles_density"])  # type: ignore[arg-type]
    if not 0.05 <= density <= 10.0:
        raise BackendError(
            ErrorCode.INVALID_OPTION, "option vehicles_density must be within [0.05, 10]"
        )
    interval = float(options["decision_interval"])  # type: ignore[arg-type]
    substeps = round(interval * SIMULATION_FREQUENCY)
    if substeps < 1 or abs(substeps * DT - interval) > 1e-6:
        raise BackendError(
            ErrorCode.INVALID_OPTION,
            f"decision_interval {interval} s is not a multiple of the step length {DT} s",
        )
    return substeps


def _limit_acceleration(
    request: float, speed: float, limit: float, low: float, high: float, dt: float
) -> tuple[float, str]:
    """Clip to the bounds, then keep 0 <= next speed <= limit; says which rule bound it."""
    applied = min(max(request, low), high)
    why = "bounds" if applied != request else ""
    if speed + applied * dt > limit:
        applied, why = max((limit - speed) / dt, low), "speed_limit"
    if speed + applied * dt < 0.0:
        applied, why = -speed / dt, "standstill"
    return applied, why
