"""SUMO behind the bridge, in-process through libsumo (one simulation per process).

The ego is driven entirely by the client: speed mode 32 switches SUMO's safety checks off (the
agent can crash and must learn not to), lane-change mode 512 stops SUMO's own lane changes but
keeps its gap check on requested ones (a refused change is the paper's state G). Actions are
clipped to the announced bounds and to the road's speed limit here, because speed mode 32 would
obey anything. Collisions are real overlaps (``collision.mingap-factor 0``) and are checked before
arrival, so a crash at the end of the road is still a crash.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import libsumo

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
from sim_server.backend import Backend, BackendError
from sim_server.scenarios import (
    BUILTIN_SCENARIOS,
    EGO_ID,
    EGO_ROUTE,
    EGO_TYPE,
    HUMAN_TYPE,
    CustomScenario,
    RoadScenario,
    Scenario,
    build_road,
    check_options,
    default_cache_dir,
)

SPEED_MODE_NO_CHECKS = 32
LANE_CHANGE_MODE_REQUESTS_ONLY = 512
CEILING_HORIZON = 3600.0
"""Longest extra simulated time (s) spent waiting for the leader-at-entry to arrive."""

_SUMO_ERRORS = (libsumo.TraCIException, libsumo.FatalTraCIError)

# Command-line options forced on every scenario, also a user's own .sumocfg.
_FORCED_ARGS = [
    "--collision.action", "warn",
    "--collision.mingap-factor", "0",
    "--time-to-teleport", "-1",
    "--lanechange.duration", "2",
    "--no-step-log", "true",
    "--no-warnings", "true",
]  # fmt: skip

_ABSENT = Neighbour(present=False, gap=0.0, lateral=0.0, speed=0.0)


@dataclass
class _Episode:
    """Book-keeping of the running episode."""

    dt: float
    substeps: int
    options: dict[str, OptionValue]
    entry_time: float
    entry_offset: float
    route_length: float
    leader_id: str
    leader_depart: float
    leader_arrival: float | None = None
    sumo_drives: bool = False
    lane_change_target: int | None = None
    stopped_since: float | None = None
    done: bool = False
    last: Observation | None = None
    lane_counts: dict[str, int] = field(default_factory=dict)


class SumoBackend(Backend):
    """Runs SUMO scenarios through libsumo; reset reloads the running SUMO when it can."""

    name = "sumo"

    def __init__(
        self,
        cache_dir: Path | None = None,
        custom: tuple[CustomScenario, ...] = (),
        restart_every: int = 50,
    ) -> None:
        self._cache_dir = cache_dir or default_cache_dir()
        self._scenarios: dict[str, Scenario] = {**BUILTIN_SCENARIOS}
        for scenario in custom:
            self._scenarios[scenario.name] = scenario
        self._restart_every = restart_every
        self._loads = 0
        self._running = False
        self._episode: _Episode | None = None
        self._absent = replace(_ABSENT, gap=self.sensor_range)
        _, version = libsumo.simulation.getVersion()
        self._version = version.removeprefix("SUMO ").strip()

    @property
    def version(self) -> str:
        return self._version

    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        return tuple(s.info() for s in self._scenarios.values())

    # ----------------------------------------------------------------------- reset

    def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
        chosen = self._scenarios[scenario]
        check_options(options)
        self._episode = None
        try:
            config, route = self._files(chosen, options)
            self._load(["-c", str(config), "--seed", str(seed), *_FORCED_ARGS])
            return self._insert_ego(route, options)
        except _SUMO_ERRORS as exc:
            self._broken()
            raise BackendError(
                ErrorCode.SIMULATOR_ERROR, f"SUMO failed during reset: {exc}"
            ) from exc

    def _files(self, scenario: Scenario, options: dict[str, OptionValue]) -> tuple[Path, str]:
        if isinstance(scenario, RoadScenario):
            try:
                return build_road(scenario, options, self._cache_dir), EGO_ROUTE
            except (OSError, RuntimeError) as exc:
                raise BackendError(
                    ErrorCode.SIMULATOR_ERROR, f"could not build scenario {scenario.name}: {exc}"
                ) from exc
        return scenario.sumocfg, scenario.ego_route

    def _load(self, args: list[str]) -> None:
        if self._running and self._loads < self._restart_every:
            libsumo.simulation.load(args)
            self._loads += 1
            return
        if self._running:
            libsumo.close()
        libsumo.start(["sumo", *args])
        self._running = True
        self._loads = 0

    def _insert_ego(self, route: str, options: dict[str, OptionValue]) -> Observation:
        dt = libsumo.simulation.getDeltaT()
        interval = float(options["decision_interval"])  # type: ignore[arg-type]
        substeps = round(interval / dt)
        if substeps < 1 or abs(substeps * dt - interval) > 1e-6:
            raise BackendError(
                ErrorCode.INVALID_OPTION,
                f"decision_interval {interval} s is not a multiple of the step length {dt} s",
            )
        libsumo.simulationStep(libsumo.simulation.getTime() + float(options["warmup"]))  # type: ignore[arg-type]
        sumo_drives = options["ego_driver"] == "sumo"
        types = libsumo.vehicletype.getIDList()
        if sumo_drives:  # a human driver of the scenario, driven by SUMO, observed by the client
            type_id = HUMAN_TYPE if HUMAN_TYPE in types else "DEFAULT_VEHTYPE"
        else:
            type_id = EGO_TYPE
            if EGO_TYPE not in types:
                self._define_ego_type()
        libsumo.vehicle.add(
            EGO_ID, route, typeID=type_id, depart="now",
            departLane="random", departPos="base", departSpeed="max",
        )  # fmt: skip
        if not sumo_drives:
            libsumo.vehicle.setSpeedMode(EGO_ID, SPEED_MODE_NO_CHECKS)
            libsumo.vehicle.setLaneChangeMode(EGO_ID, LANE_CHANGE_MODE_REQUESTS_ONLY)
        deadline = libsumo.simulation.getTime() + float(options["insertion_timeout"])  # type: ignore[arg-type]
        while EGO_ID not in libsumo.simulation.getDepartedIDList():
            if libsumo.simulation.getTime() >= deadline:
                libsumo.vehicle.remove(EGO_ID)
                raise BackendError(
                    ErrorCode.INSERTION_FAILED,
                    f"the ego could not enter within {options['insertion_timeout']} s "
                    "(road too full at the entry); try a lower flow or another seed",
                )
            libsumo.simulationStep()
        edges = libsumo.vehicle.getRoute(EGO_ID)
        route_length = sum(libsumo.lane.getLength(f"{edge}_0") for edge in edges)
        leader_id, _ = libsumo.vehicle.getLeader(EGO_ID, route_length) or ("", 0.0)
        self._episode = _Episode(
            dt=dt,
            substeps=substeps,
            options=options,
            entry_time=libsumo.simulation.getTime(),
            entry_offset=libsumo.vehicle.getLanePosition(EGO_ID),
            route_length=route_length,
            leader_id=leader_id,
            leader_depart=libsumo.vehicle.getDeparture(leader_id) if leader_id else math.nan,
            sumo_drives=sumo_drives,
        )
        action = AppliedAction(0.0, 0, 0.0, 0)
        return self._observe(self._episode, 0, Events(), action)

    @staticmethod
    def _define_ego_type() -> None:
        """A user's .sumocfg has no ego type: derive one like the built-in scenarios'."""
        libsumo.vehicletype.copy("DEFAULT_VEHTYPE", EGO_TYPE)
        libsumo.vehicletype.setImperfection(EGO_TYPE, 0.0)
        libsumo.vehicletype.setSpeedFactor(EGO_TYPE, 1.0)
        libsumo.vehicletype.setSpeedDeviation(EGO_TYPE, 0.0)
        libsumo.vehicletype.setAccel(EGO_TYPE, 3.0)
        libsumo.vehicletype.setDecel(EGO_TYPE, 6.0)
        libsumo.vehicletype.setEmergencyDecel(EGO_TYPE, 9.0)

    # ----------------------------------------------------------------------- step

    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        episode = self._episode
        if episode is None or episode.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        try:
            return self._step(episode, seq, acceleration, lane_change)
        except _SUMO_ERRORS as exc:
            self._broken()
            raise BackendError(
                ErrorCode.SIMULATOR_ERROR, f"SUMO failed during step: {exc}"
            ) from exc

    def _step(self, episode: _Episode, seq: int, request: float, lane_change: int) -> Observation:
        started = False
        if episode.sumo_drives:
            refused = "simulator_drives" if lane_change else ""
        else:
            refused = self._lane_change_refusal(episode, lane_change) if lane_change else ""
        if lane_change and not refused:
            target = libsumo.vehicle.getLaneIndex(EGO_ID) + lane_change
            libsumo.vehicle.changeLane(EGO_ID, target, 2.0)
            episode.lane_change_target = target
            started = True
        low = self.action_schema.acceleration_min
        high = self.action_schema.acceleration_max
        applied_total, limited_by = 0.0, ""
        collision_with, end_of_road, completed, teleported = "", False, False, False
        substeps_done = 0
        for _ in range(episode.substeps):
            if episode.sumo_drives:
                libsumo.simulationStep()
                gone = EGO_ID in libsumo.simulation.getArrivedIDList()
                applied = 0.0 if gone else libsumo.vehicle.getAcceleration(EGO_ID)
                why = "simulator"
            else:
                speed = libsumo.vehicle.getSpeed(EGO_ID)
                limit = libsumo.vehicle.getAllowedSpeed(EGO_ID)
                applied, why = _limit_acceleration(request, speed, limit, low, high, episode.dt)
                libsumo.vehicle.setAcceleration(EGO_ID, applied, episode.dt)
                libsumo.simulationStep()
            applied_total += applied
            limited_by = limited_by or why
            substeps_done += 1
            for collision in libsumo.simulation.getCollisions():
                if collision.collider == EGO_ID:
                    collision_with = collision.victim
                elif collision.victim == EGO_ID:
                    collision_with = collision.collider
            arrived = libsumo.simulation.getArrivedIDList()
            if episode.leader_arrival is None and episode.leader_id in arrived:
                episode.leader_arrival = libsumo.simulation.getTime()
            teleported = teleported or EGO_ID in libsumo.simulation.getStartingTeleportIDList()
            if collision_with:
                break
            if EGO_ID in arrived:
                end_of_road = True
                break
            if episode.lane_change_target is not None and _lane_change_done(episode):
                episode.lane_change_target = None
                completed = True
        action = AppliedAction(
            requested_acceleration=request,
            requested_lane_change=lane_change,
            acceleration=applied_total / substeps_done,
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
            teleported=teleported,
        )
        if end_of_road:
            return self._finish(episode, self._arrival_observation(episode, seq, events, action))
        if teleported or EGO_ID not in libsumo.vehicle.getIDList():
            obs = replace(
                self._arrival_observation(episode, seq, events, action),
                terminated=True,
                reason="ego_lost",
            )
            return self._finish(episode, obs)
        obs = self._observe(episode, seq, events, action)
        reason = self._termination(episode, obs)
        if reason:
            truncated = reason == "time_limit"
            obs = replace(obs, terminated=not truncated, truncated=truncated, reason=reason)
            return self._finish(episode, obs)
        return obs

    def _lane_change_refusal(self, episode: _Episode, direction: int) -> str:
        if episode.lane_change_target is not None:
            return "in_progress"
        lane = libsumo.vehicle.getLaneIndex(EGO_ID)
        if not 0 <= lane + direction < self._lane_count(episode):
            return "no_lane"
        if not libsumo.vehicle.couldChangeLane(EGO_ID, direction):
            return "gap_too_small"
        return ""

    def _termination(self, episode: _Episode, obs: Observation) -> str:
        options = episode.options
        if obs.events.collision:
            return "collision"
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

    def _finish(self, episode: _Episode, obs: Observation) -> Observation:
        """End the episode: take the ego out and report the leader-at-entry's trip."""
        episode.done = True
        if EGO_ID in libsumo.vehicle.getIDList():
            libsumo.vehicle.remove(EGO_ID)
        if episode.options["report_ceiling"]:
            obs = replace(obs, ceiling=self._leader_trip(episode))
        return obs

    def _leader_trip(self, episode: _Episode) -> LeaderTrip | None:
        if not episode.leader_id:
            return None
        end = libsumo.simulation.getTime() + CEILING_HORIZON
        while episode.leader_arrival is None and libsumo.simulation.getTime() < end:
            libsumo.simulationStep()
            if episode.leader_id in libsumo.simulation.getArrivedIDList():
                episode.leader_arrival = libsumo.simulation.getTime()
        arrival = episode.leader_arrival
        average = (
            None if arrival is None else episode.route_length / (arrival - episode.leader_depart)
        )
        return LeaderTrip(episode.leader_id, episode.leader_depart, arrival, average)

    # ----------------------------------------------------------------------- observation

    def _lane_count(self, episode: _Episode) -> int:
        road = libsumo.vehicle.getRoadID(EGO_ID)
        count = episode.lane_counts.get(road)
        if count is None:
            count = episode.lane_counts[road] = libsumo.edge.getLaneNumber(road)
        return count

    def _observe(
        self, episode: _Episode, seq: int, events: Events, action: AppliedAction
    ) -> Observation:
        vehicle = libsumo.vehicle
        ego = Ego(
            speed=vehicle.getSpeed(EGO_ID),
            acceleration=vehicle.getAcceleration(EGO_ID),
            lane=vehicle.getLaneIndex(EGO_ID),
            lane_count=self._lane_count(episode),
            position=episode.entry_offset + vehicle.getDistance(EGO_ID),
            speed_limit=libsumo.lane.getMaxSpeed(vehicle.getLaneID(EGO_ID)),
        )
        x, y = vehicle.getPosition(EGO_ID)
        heading = math.radians(vehicle.getAngle(EGO_ID))
        frame = (x, y, -math.cos(heading), math.sin(heading))
        ego_min_gap = vehicle.getMinGap(EGO_ID)
        sensed = self.sensor_range
        leader = vehicle.getLeader(EGO_ID, sensed)
        follower = vehicle.getFollower(EGO_ID, sensed)
        neighbours = Neighbours(
            left_leader=self._nearest(vehicle.getNeighbors(EGO_ID, 0b010), ego_min_gap, frame),
            left_follower=self._nearest(vehicle.getNeighbors(EGO_ID, 0b000), None, frame),
            leader=self._nearest((leader,) if leader and leader[0] else (), ego_min_gap, frame),
            follower=self._nearest((follower,) if follower and follower[0] else (), None, frame),
            right_leader=self._nearest(vehicle.getNeighbors(EGO_ID, 0b011), ego_min_gap, frame),
            right_follower=self._nearest(vehicle.getNeighbors(EGO_ID, 0b001), None, frame),
        )
        obs = Observation(
            seq=seq,
            time=libsumo.simulation.getTime(),
            ego=ego,
            neighbours=neighbours,
            events=events,
            action=action,
        )
        episode.last = obs
        return obs

    def _nearest(
        self,
        found: Any,
        ego_min_gap: float | None,
        frame: tuple[float, float, float, float],
    ) -> Neighbour:
        """The closest of (id, distance) pairs as a Neighbour with the net bumper gap.

        SUMO's leader distance excludes the ego's minGap, its follower distance the follower's:
        `ego_min_gap` is given for leaders, None for followers.
        """
        if not found:
            return self._absent
        other, distance = min(found, key=lambda pair: pair[1])
        gap = distance + (
            ego_min_gap if ego_min_gap is not None else libsumo.vehicle.getMinGap(other)
        )
        if gap > self.sensor_range:
            return self._absent
        x, y, normal_x, normal_y = frame
        other_x, other_y = libsumo.vehicle.getPosition(other)
        lateral = (other_x - x) * normal_x + (other_y - y) * normal_y
        return Neighbour(True, gap, lateral, libsumo.vehicle.getSpeed(other), other)

    def _arrival_observation(
        self, episode: _Episode, seq: int, events: Events, action: AppliedAction
    ) -> Observation:
        """The ego has left the network: extrapolate its last observed state by one decision."""
        last = episode.last
        assert last is not None
        elapsed = episode.dt * episode.substeps
        ego = replace(
            last.ego,
            speed=max(0.0, last.ego.speed + action.acceleration * elapsed),
            acceleration=action.acceleration,
            position=episode.route_length,
        )
        return replace(
            last,
            seq=seq,
            time=libsumo.simulation.getTime(),
            ego=ego,
            events=events,
            action=action,
            terminated=True,
            reason="end_of_road",
        )

    # ----------------------------------------------------------------------- lifecycle

    def _broken(self) -> None:
        """After a SUMO failure, start afresh on the next reset."""
        self._episode = None
        if self._running:
            with contextlib.suppress(*_SUMO_ERRORS):  # already gone: start() will follow
                libsumo.close()
        self._running = False

    def close(self) -> None:
        self._broken()


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


def _lane_change_done(episode: _Episode) -> bool:
    return (
        libsumo.vehicle.getLaneIndex(EGO_ID) == episode.lane_change_target
        and abs(libsumo.vehicle.getLateralLanePosition(EGO_ID)) < 1e-6
    )
