"""SUMO behind the bridge: in-process through libsumo, or over TraCI to a sumo / sumo-gui process.

libsumo and TraCI have the same API, so one `SumoBackend` drives either: ``libsumo`` (the
default, one simulation per process, fastest) or a TraCI `Connection` to a ``sumo`` or
``sumo-gui`` process it starts from the eclipse-sumo wheel (or attaches to, on a port), to watch
the ego in the GUI or to share the simulation with another TraCI tool.

The ego is driven entirely by the client: speed mode 32 switches SUMO's safety checks off (the
agent can crash and must learn not to), lane-change mode 512 stops SUMO's own lane changes but
keeps its gap check on requested ones (a refused change is the paper's state G). Actions are
clipped to the announced bounds and to the road's speed limit here, because speed mode 32 would
obey anything. Collisions are real overlaps (``collision.mingap-factor 0``) and are checked before
arrival, so a crash at the end of the road is still a crash.

On the ``ring`` every vehicle is placed at reset: the ego is one of the human drivers during the
warm-up and is handed to the client (its type switched to the ego's) when the warm-up ends.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import shutil
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from protocol.errors import ErrorCode
from protocol.messages import (
    AccelerationLimit,
    AppliedAction,
    Ego,
    EndReason,
    Events,
    LeaderTrip,
    Neighbour,
    Neighbours,
    Observation,
    OptionValue,
    Safety,
    ScenarioInfo,
    Traffic,
)
from sim_server.backends.base import Backend
from sim_server.backends.options import EpisodeOptions, TrafficOptions
from sim_server.backends.rules import (
    EndRule,
    LaneChangeUnderWay,
    ended,
    lane_change_refusal,
    limit_acceleration,
)
from sim_server.backends.sumo import ssm
from sim_server.backends.sumo.runtime import InProcess, OverTraci, check_display
from sim_server.backends.sumo.scenarios import (
    BUILTIN_SCENARIOS,
    EGO_ID,
    EGO_ROUTE,
    EGO_TYPE,
    HUMAN_TYPE,
    CustomScenario,
    MeasureOptions,
    RingOptions,
    RingScenario,
    RoadScenario,
    Scenario,
    build_ring,
    build_road,
    default_cache_dir,
)
from sim_server.backends.sumo.traffic import observe_traffic
from sim_server.errors import BackendError

SPEED_MODE_NO_CHECKS = 32
LANE_CHANGE_MODE_REQUESTS_ONLY = 512
CEILING_HORIZON = 3600.0
"""Longest extra simulated time (s) spent waiting for the leader-at-entry to arrive."""

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
_QUIET = Events()
"""The events of most steps (nothing happened); immutable, so shared."""


@dataclass
class _Episode:
    """Book-keeping of the running episode."""

    dt: float
    substeps: int
    options: EpisodeOptions
    measures: MeasureOptions
    end: EndRule
    entry_offset: float
    route_length: float
    leader_id: str
    leader_depart: float
    leader_arrival: float | None = None
    sumo_drives: bool = False
    one_way: bool = False
    """A built-in road: no lane beyond its edge's outer lanes (no opposite-direction lanes)."""
    curved: bool = False
    """The ring: one curved lane, where an offset across the ego's heading would be the
    curvature's; neighbours' `lateral` is 0 there."""
    lane_change: LaneChangeUnderWay | None = None
    done: bool = False
    last: Observation | None = None
    ego_min_gap: float = 0.0
    lanes: dict[str, tuple[int, int]] = field(default_factory=dict)
    """Lane id -> (its index, the lane count of its edge): neither changes during a run."""
    min_gaps: dict[str, float] = field(default_factory=dict)
    """Vehicle id -> its minGap (fixed by its type)."""
    ssm_log: Path | None = None
    """Where SUMO's SSM device logs the ego's conflicts (reset option ``ssm``)."""


class SumoBackend(Backend):
    """Runs SUMO scenarios; reset reloads the running SUMO when it can.

    By default SUMO runs in this process through libsumo. With ``traci=True`` it runs in a
    ``sumo`` process (``sumo-gui`` with ``gui=True``) driven over TraCI, or, with `traci_port`,
    in a SUMO another tool started with ``--remote-port``. Same scenarios, same observations.
    """

    name = "sumo"

    def __init__(
        self,
        cache_dir: Path | None = None,
        custom: tuple[CustomScenario, ...] = (),
        restart_every: int = 50,
        *,
        traci: bool = False,
        gui: bool = False,
        traci_port: int | None = None,
        traci_host: str = "localhost",
        sumo_binary: str | None = None,
        view: Any = None,
    ) -> None:
        if not traci and (gui or traci_port is not None or sumo_binary is not None):
            raise ValueError("gui, traci_port and sumo_binary need traci=True")
        if view is not None and not gui:
            raise ValueError("a GUI view needs gui=True")
        if gui and traci_port is not None:
            raise ValueError("gui starts its own sumo-gui: it cannot attach to a port")
        if gui:
            check_display()
        self._cache_dir = cache_dir or default_cache_dir()
        self._scenarios: dict[str, Scenario] = {**BUILTIN_SCENARIOS}
        for scenario in custom:
            self._scenarios[scenario.name] = scenario
        over_traci = OverTraci(gui, traci_port, traci_host, sumo_binary, view) if traci else None
        self._sumo: InProcess | OverTraci = over_traci or InProcess()
        self.name = self._sumo.name
        self._errors = self._sumo.errors
        self._api: Any = None
        self._restart_every = restart_every
        self._loads = 0
        self._running = False
        self._episode: _Episode | None = None
        self._absent = replace(_ABSENT, gap=self.sensor_range)
        self._logs: Path | None = None
        """A temporary folder of SSM logs, made when first needed."""
        self._log_numbers = itertools.count()
        if over_traci is not None and traci_port is not None:
            try:
                self._api = over_traci.attach()
            except self._errors as exc:
                where = f"{traci_host}:{traci_port}"
                raise ValueError(f"cannot attach to SUMO at {where}: {exc}") from exc
            self._running = True
        self._version = self._sumo.version()

    @property
    def version(self) -> str:
        return self._version

    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        return tuple(s.info() for s in self._scenarios.values())

    # ----------------------------------------------------------------------- reset

    def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
        chosen = self._scenarios[scenario]
        episode_options = EpisodeOptions.parse(options)
        traffic = TrafficOptions.parse(options) if isinstance(chosen, RoadScenario) else None
        layout = RingOptions.parse(options) if isinstance(chosen, RingScenario) else None
        measures = MeasureOptions.parse(options)
        self._episode = None
        try:
            config, route = self._files(chosen, traffic or layout)
            log = self._new_ssm_log() if measures.ssm else None
            device = ssm.device_args(EGO_ID, log) if log is not None else []
            self._load(["-c", str(config), "--seed", str(seed), *_FORCED_ARGS, *device])
            self._drop_old_logs(keep=log)
            if layout is not None:
                first = self._place_ego(layout, episode_options, measures)
            else:
                first = self._insert_ego(
                    route, episode_options, measures, one_way=traffic is not None
                )
            assert self._episode is not None
            self._episode.ssm_log = log
            self._sumo.ego_ready(self._api, EGO_ID)
            return first
        except self._errors as exc:
            self._broken(exc)
            raise BackendError(
                ErrorCode.SIMULATOR_ERROR, f"SUMO failed during reset: {exc}"
            ) from exc

    def _files(
        self, scenario: Scenario, parsed: TrafficOptions | RingOptions | None
    ) -> tuple[Path, str]:
        """The scenario's .sumocfg (a built-in one built from its `parsed` options) and the
        ego's route (the ring's ego is placed by `_place_ego` instead)."""
        if isinstance(scenario, CustomScenario):
            return scenario.sumocfg, scenario.ego_route
        try:
            if isinstance(scenario, RingScenario):
                assert isinstance(parsed, RingOptions)
                return build_ring(scenario, parsed, self._cache_dir), ""
            assert isinstance(parsed, TrafficOptions)
            return build_road(scenario, parsed, self._cache_dir), EGO_ROUTE
        except (OSError, RuntimeError) as exc:
            raise BackendError(
                ErrorCode.SIMULATOR_ERROR, f"could not build scenario {scenario.name}: {exc}"
            ) from exc

    def _load(self, args: list[str]) -> None:
        if self._running and (self._loads < self._restart_every or not self._sumo.restarts):
            self._sumo.load(self._api, args)
            self._loads += 1
            return
        if self._running:
            self._sumo.close(self._api)
            self._running = False
        self._api = self._sumo.start(args)
        self._running = True
        self._loads = 0

    def _insert_ego(
        self, route: str, options: EpisodeOptions, measures: MeasureOptions, one_way: bool
    ) -> Observation:
        """Warm up, insert the ego at the start of `route` and observe it (seq 0)."""
        api = self._api
        dt = api.simulation.getDeltaT()
        substeps = options.steps_per_decision(dt)
        api.simulationStep(api.simulation.getTime() + options.warmup)
        self._add_ego(route, options.simulator_drives)
        self._wait_for_entry(options.insertion_timeout)
        edges = api.vehicle.getRoute(EGO_ID)
        route_length = sum(api.lane.getLength(f"{edge}_0") for edge in edges)
        leader_id, _ = api.vehicle.getLeader(EGO_ID, route_length) or ("", 0.0)
        self._episode = _Episode(
            dt=dt,
            substeps=substeps,
            options=options,
            measures=measures,
            end=EndRule(options, entry_time=api.simulation.getTime()),
            entry_offset=api.vehicle.getLanePosition(EGO_ID),
            route_length=route_length,
            leader_id=leader_id,
            leader_depart=api.vehicle.getDeparture(leader_id) if leader_id else math.nan,
            sumo_drives=options.simulator_drives,
            one_way=one_way,
            ego_min_gap=api.vehicle.getMinGap(EGO_ID),
        )
        action = AppliedAction(0.0, 0, 0.0, 0)
        return self._observe(self._episode, 0, Events(), action)

    def _place_ego(
        self, layout: RingOptions, options: EpisodeOptions, measures: MeasureOptions
    ) -> Observation:
        """The ring: the ego joins the humans in slot 0, drives as one of them through the
        warm-up, and is handed over at its end (seq 0)."""
        api = self._api
        dt = api.simulation.getDeltaT()
        substeps = options.steps_per_decision(dt)
        route, position = layout.slot(0)
        api.vehicle.add(
            EGO_ID, route, typeID=HUMAN_TYPE, depart="now",
            departLane="0", departPos=f"{position:.3f}", departSpeed="0",
        )  # fmt: skip
        api.simulationStep()  # everyone enters in this first step, or the ring is refused
        self._check_ring_entry(layout.vehicles)
        api.simulationStep(max(options.warmup, api.simulation.getTime()))
        if not options.simulator_drives:
            api.vehicle.setType(EGO_ID, EGO_TYPE)
            api.vehicle.setSpeedMode(EGO_ID, SPEED_MODE_NO_CHECKS)
            api.vehicle.setLaneChangeMode(EGO_ID, LANE_CHANGE_MODE_REQUESTS_ONLY)
        self._episode = _Episode(
            dt=dt,
            substeps=substeps,
            options=options,
            measures=measures,
            end=EndRule(options, entry_time=api.simulation.getTime()),
            entry_offset=layout.ring_position(0),
            route_length=layout.laps() * layout.ring_length,
            leader_id="",  # nobody arrives on a ring: no leader-at-entry trip (ceiling nil)
            leader_depart=math.nan,
            sumo_drives=options.simulator_drives,
            one_way=True,
            curved=True,
            ego_min_gap=api.vehicle.getMinGap(EGO_ID),
        )
        action = AppliedAction(0.0, 0, 0.0, 0)
        return self._observe(self._episode, 0, Events(), action)

    def _check_ring_entry(self, vehicles: int) -> None:
        """Every vehicle of the ring entered in the first step (placed, so they must)."""
        entered = self._api.simulation.getDepartedIDList()
        if EGO_ID not in entered or len(entered) != vehicles:
            raise BackendError(
                ErrorCode.INSERTION_FAILED,
                f"only {len(entered)} of the ring's {vehicles} vehicles could be placed",
            )

    def _add_ego(self, route: str, sumo_drives: bool) -> None:
        """Ask SUMO to insert the ego now: the client's (SUMO's checks off) or a human."""
        api = self._api
        types = api.vehicletype.getIDList()
        if sumo_drives:  # a human driver of the scenario, driven by SUMO, observed by the client
            type_id = HUMAN_TYPE if HUMAN_TYPE in types else "DEFAULT_VEHTYPE"
        else:
            type_id = EGO_TYPE
            if EGO_TYPE not in types:
                self._define_ego_type()
        api.vehicle.add(
            EGO_ID, route, typeID=type_id, depart="now",
            departLane="random", departPos="base", departSpeed="max",
        )  # fmt: skip
        if not sumo_drives:
            api.vehicle.setSpeedMode(EGO_ID, SPEED_MODE_NO_CHECKS)
            api.vehicle.setLaneChangeMode(EGO_ID, LANE_CHANGE_MODE_REQUESTS_ONLY)

    def _wait_for_entry(self, timeout: float) -> None:
        """Step until the ego has entered; give up after `timeout` s of simulation."""
        api = self._api
        deadline = api.simulation.getTime() + timeout
        while EGO_ID not in api.simulation.getDepartedIDList():
            if api.simulation.getTime() >= deadline:
                api.vehicle.remove(EGO_ID)
                raise BackendError(
                    ErrorCode.INSERTION_FAILED,
                    f"the ego could not enter within {timeout} s "
                    "(road too full at the entry); try a lower flow or another seed",
                )
            api.simulationStep()

    def _define_ego_type(self) -> None:
        """A user's .sumocfg has no ego type: derive one like the built-in scenarios'."""
        api = self._api
        api.vehicletype.copy("DEFAULT_VEHTYPE", EGO_TYPE)
        api.vehicletype.setImperfection(EGO_TYPE, 0.0)
        api.vehicletype.setSpeedFactor(EGO_TYPE, 1.0)
        api.vehicletype.setSpeedDeviation(EGO_TYPE, 0.0)
        api.vehicletype.setAccel(EGO_TYPE, 3.0)
        api.vehicletype.setDecel(EGO_TYPE, 6.0)
        api.vehicletype.setEmergencyDecel(EGO_TYPE, 9.0)

    # ----------------------------------------------------------------------- step

    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        episode = self._episode
        if episode is None or episode.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        try:
            return self._step(episode, seq, acceleration, lane_change)
        except self._errors as exc:
            self._broken(exc)
            raise BackendError(
                ErrorCode.SIMULATOR_ERROR, f"SUMO failed during step: {exc}"
            ) from exc

    def _step(self, episode: _Episode, seq: int, request: float, lane_change: int) -> Observation:
        refused = self._lane_change_refusal(episode, lane_change) if lane_change else ""
        started = bool(lane_change) and not refused
        if started:
            self._start_lane_change(episode, lane_change)
        action, events = self._drive(episode, request, lane_change, refused, started)
        self._sumo.stepped(self._api, EGO_ID)
        return self._conclude(episode, seq, events, action)

    def _lane_change_refusal(self, episode: _Episode, direction: int) -> str:
        return lane_change_refusal(
            direction,
            simulator_drives=episode.sumo_drives,
            under_way=episode.lane_change,
            ego_lane=lambda: self._lane(episode),
            gap_ok=self._could_change_lane,
        )

    def _could_change_lane(self, direction: int) -> bool:
        """SUMO's own gap check of a requested change (lane-change mode 512 keeps it)."""
        return bool(self._api.vehicle.couldChangeLane(EGO_ID, direction))

    def _start_lane_change(self, episode: _Episode, direction: int) -> None:
        """Ask SUMO for the change: the request stands for 2 s, the manoeuvre takes 2 s
        (``--lanechange.duration``)."""
        target = self._lane(episode)[0] + direction
        self._api.vehicle.changeLane(EGO_ID, target, 2.0)
        now = self._api.simulation.getTime()
        episode.lane_change = LaneChangeUnderWay(target, direction, now)

    def _drive(
        self, episode: _Episode, request: float, lane_change: int, refused: str, started: bool
    ) -> tuple[AppliedAction, Events]:
        """Run the decision's simulation steps; stop early at a collision or the ego's arrival."""
        api = self._api
        applied_total, limited_by = 0.0, ""
        collision_with, end_of_road, teleported = "", False, False
        completed = aborted = False
        substeps_done = 0
        for _ in range(episode.substeps):
            applied, why = self._substep(episode, request)
            applied_total += applied
            limited_by = limited_by or why
            substeps_done += 1
            collision_with = _collision_partner(api.simulation.getCollisions())
            arrived = api.simulation.getArrivedIDList()
            if episode.leader_arrival is None and episode.leader_id in arrived:
                episode.leader_arrival = api.simulation.getTime()
            teleported = teleported or EGO_ID in api.simulation.getStartingTeleportIDList()
            if collision_with:
                break
            if EGO_ID in arrived:
                end_of_road = True
                break
            if episode.lane_change is not None:
                completed, aborted = self._lane_change_progress(episode, episode.lane_change)
        action = AppliedAction(
            requested_acceleration=request,
            requested_lane_change=lane_change,
            acceleration=applied_total / substeps_done,
            lane_change=0 if refused else lane_change,
            acceleration_limited_by=limited_by,
            lane_change_refused=refused,
        )
        events = (
            Events(
                collision=bool(collision_with),
                collision_with=collision_with,
                end_of_road=end_of_road,
                lane_change_started=started,
                lane_change_completed=completed,
                lane_change_refused=bool(refused),
                teleported=teleported,
                lane_change_aborted=aborted,
            )
            if any((collision_with, end_of_road, started, completed, aborted, refused, teleported))
            else _QUIET
        )
        return action, events

    def _substep(self, episode: _Episode, request: float) -> tuple[float, str]:
        """One simulation step: the applied acceleration and what limited it ("" nothing)."""
        api = self._api
        if episode.sumo_drives:
            api.simulationStep()
            gone = EGO_ID in api.simulation.getArrivedIDList()
            return 0.0 if gone else api.vehicle.getAcceleration(EGO_ID), AccelerationLimit.SIMULATOR
        vehicle = api.vehicle
        applied, why = limit_acceleration(
            request,
            vehicle.getSpeed(EGO_ID),
            vehicle.getAllowedSpeed(EGO_ID),
            self.action_schema.acceleration_min,
            self.action_schema.acceleration_max,
            episode.dt,
        )
        vehicle.setAcceleration(EGO_ID, applied, episode.dt)
        api.simulationStep()
        return applied, why

    def _lane_change_progress(
        self, episode: _Episode, change: LaneChangeUnderWay
    ) -> tuple[bool, bool]:
        """(completed, aborted) of the lane change under way; either ends it."""
        vehicle = self._api.vehicle
        if (
            vehicle.getLaneIndex(EGO_ID) == change.target
            and abs(vehicle.getLateralLanePosition(EGO_ID)) < 1e-6
        ):
            episode.lane_change = None
            return True, False
        if change.expired(self._api.simulation.getTime()):
            episode.lane_change = None
            return False, True
        return False, False

    def _conclude(
        self, episode: _Episode, seq: int, events: Events, action: AppliedAction
    ) -> Observation:
        """The observation after a step, the last one of the episode if a rule ends it."""
        if events.end_of_road:
            arrival = self._arrival_observation(episode, seq, events, action)
            return self._finish(episode, ended(arrival, EndReason.END_OF_ROAD))
        obs = None if events.teleported else self._observe_if_present(episode, seq, events, action)
        if obs is None:  # gone without arriving
            lost = self._arrival_observation(episode, seq, events, action)
            return self._finish(episode, ended(lost, EndReason.EGO_LOST))
        reason = episode.end.check(obs)
        return obs if reason is None else self._finish(episode, ended(obs, reason))

    def _observe_if_present(
        self, episode: _Episode, seq: int, events: Events, action: AppliedAction
    ) -> Observation | None:
        """The observation, or None if the ego has left without arriving (its state cannot be
        read)."""
        try:
            return self._observe(episode, seq, events, action)
        except self._errors:
            if EGO_ID in self._api.vehicle.getIDList():
                raise
            return None

    def _finish(self, episode: _Episode, obs: Observation) -> Observation:
        """End the episode: take the ego out and report the leader-at-entry's trip."""
        api = self._api
        episode.done = True
        if EGO_ID in api.vehicle.getIDList():
            api.vehicle.remove(EGO_ID)
        if episode.options.report_ceiling:
            obs = replace(obs, ceiling=self._leader_trip(episode))
        if episode.ssm_log is not None:
            obs = replace(obs, safety=self._conflicts(episode, episode.ssm_log))
        return obs

    def _new_ssm_log(self) -> Path:
        """A fresh file name for the next episode's SSM log."""
        if self._logs is None:
            self._logs = Path(tempfile.mkdtemp(prefix="av-bridge-ssm-"))
        return self._logs / f"ssm-{next(self._log_numbers)}.xml"

    def _drop_old_logs(self, keep: Path | None) -> None:
        """Delete the logs of abandoned episodes (SUMO has written them out by now)."""
        if self._logs is not None:
            for old in self._logs.iterdir():
                if old != keep:
                    old.unlink(missing_ok=True)

    def _conflicts(self, episode: _Episode, log: Path) -> Safety:
        """The ego's conflicts from the SSM log, which SUMO writes out when the simulation is
        closed: load the small built-in ``cf`` road (not the scenario again, whose own outputs
        would be overwritten), read the log, delete it. Over TraCI a load is acknowledged before
        the old simulation has closed; a round trip after it waits for that."""
        config, _ = self._files(BUILTIN_SCENARIOS["cf"], TrafficOptions())
        self._load(["-c", str(config), *_FORCED_ARGS])
        self._api.simulation.getTime()
        try:
            return ssm.read_log(log, episode.dt, since=episode.end.entry_time)
        except ssm.LogError as exc:
            raise BackendError(ErrorCode.SIMULATOR_ERROR, str(exc)) from exc
        finally:
            log.unlink(missing_ok=True)

    def _leader_trip(self, episode: _Episode) -> LeaderTrip | None:
        api = self._api
        if not episode.leader_id:
            return None
        end = api.simulation.getTime() + CEILING_HORIZON
        while episode.leader_arrival is None and api.simulation.getTime() < end:
            api.simulationStep()
            if episode.leader_id in api.simulation.getArrivedIDList():
                episode.leader_arrival = api.simulation.getTime()
        arrival = episode.leader_arrival
        average = (
            None if arrival is None else episode.route_length / (arrival - episode.leader_depart)
        )
        return LeaderTrip(episode.leader_id, episode.leader_depart, arrival, average)

    # ----------------------------------------------------------------------- observation

    def _lane(self, episode: _Episode, lane_id: str | None = None) -> tuple[int, int]:
        """The ego's lane index and the number of lanes of its edge (one query when cached)."""
        api = self._api
        if lane_id is None:
            lane_id = api.vehicle.getLaneID(EGO_ID)
        known = episode.lanes.get(lane_id)
        if known is None:
            road = api.lane.getEdgeID(lane_id)
            known = episode.lanes[lane_id] = (
                api.vehicle.getLaneIndex(EGO_ID),
                api.edge.getLaneNumber(road),
            )
        return known

    def _observe(
        self, episode: _Episode, seq: int, events: Events, action: AppliedAction
    ) -> Observation:
        vehicle = self._api.vehicle
        speed = vehicle.getSpeed(EGO_ID)  # first: raises if the ego has gone
        acceleration = vehicle.getAcceleration(EGO_ID)
        lane_id = vehicle.getLaneID(EGO_ID)
        lane, lane_count = self._lane(episode, lane_id)
        ego = Ego(
            speed=speed,
            acceleration=acceleration,
            lane=lane,
            lane_count=lane_count,
            position=episode.entry_offset + vehicle.getDistance(EGO_ID),
            speed_limit=self._api.lane.getMaxSpeed(lane_id),
            changing_lane=0 if episode.lane_change is None else episode.lane_change.direction,
        )
        frame = None if episode.curved else self._frame()
        ego_min_gap = episode.ego_min_gap
        sensed = self.sensor_range
        leader = vehicle.getLeader(EGO_ID, sensed)
        follower = vehicle.getFollower(EGO_ID, sensed)
        # SUMO finds no neighbour where there is no lane: on a built-in road, skip those queries.
        left = not episode.one_way or lane + 1 < lane_count
        right = not episode.one_way or lane > 0
        nearest, none = self._nearest, ()
        neighbours = Neighbours(
            left_leader=nearest(
                episode, vehicle.getNeighbors(EGO_ID, 0b010) if left else none, ego_min_gap, frame
            ),
            left_follower=nearest(
                episode, vehicle.getNeighbors(EGO_ID, 0b000) if left else none, None, frame
            ),
            leader=nearest(
                episode, (leader,) if leader and leader[0] else none, ego_min_gap, frame
            ),
            follower=nearest(
                episode, (follower,) if follower and follower[0] else none, None, frame
            ),
            right_leader=nearest(
                episode, vehicle.getNeighbors(EGO_ID, 0b011) if right else none, ego_min_gap, frame
            ),
            right_follower=nearest(
                episode, vehicle.getNeighbors(EGO_ID, 0b001) if right else none, None, frame
            ),
        )
        obs = Observation(
            seq=seq,
            time=self._api.simulation.getTime(),
            ego=ego,
            neighbours=neighbours,
            events=events,
            action=action,
            traffic=self._traffic(episode),
        )
        episode.last = obs
        return obs

    def _traffic(self, episode: _Episode) -> Traffic | None:
        """Every other vehicle (reset option ``report_traffic``), or None."""
        if not episode.measures.report_traffic:
            return None
        return observe_traffic(self._api, EGO_ID, self.sensor_range, episode.min_gaps)

    def _frame(self) -> tuple[float, float, float, float]:
        """The ego's position and the unit normal to the left of its heading."""
        x, y = self._api.vehicle.getPosition(EGO_ID)
        heading = math.radians(self._api.vehicle.getAngle(EGO_ID))
        return (x, y, -math.cos(heading), math.sin(heading))

    def _nearest(
        self,
        episode: _Episode,
        found: Any,
        ego_min_gap: float | None,
        frame: tuple[float, float, float, float] | None,
    ) -> Neighbour:
        """The closest of (id, distance) pairs as a Neighbour with the net bumper gap.

        SUMO's leader distance excludes the ego's minGap, its follower distance the follower's:
        `ego_min_gap` is given for leaders, None for followers. Its lateral offset is measured
        across the ego's heading (`frame`), or 0 without a frame (one curved lane).
        """
        api = self._api
        if not found:
            return self._absent
        other, distance = found[0] if len(found) == 1 else min(found, key=_second)
        if ego_min_gap is None:
            min_gap = episode.min_gaps.get(other)
            if min_gap is None:
                min_gap = episode.min_gaps[other] = api.vehicle.getMinGap(other)
            gap = distance + min_gap
        else:
            gap = distance + ego_min_gap
        if gap > self.sensor_range:
            return self._absent
        lateral = 0.0
        if frame is not None:
            x, y, normal_x, normal_y = frame
            other_x, other_y = api.vehicle.getPosition(other)
            lateral = (other_x - x) * normal_x + (other_y - y) * normal_y
        return Neighbour(True, gap, lateral, api.vehicle.getSpeed(other), other)

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
            time=self._api.simulation.getTime(),
            ego=ego,
            events=events,
            action=action,
            traffic=self._traffic(episode),
        )

    # ----------------------------------------------------------------------- lifecycle

    def _broken(self, error: BaseException | None = None) -> None:
        """After a SUMO failure, start afresh on the next reset."""
        self._episode = None
        if error is not None and self._sumo.survives(error):
            return  # the next reset reloads the same SUMO
        if self._running:
            with contextlib.suppress(*self._errors):  # already gone: start() will follow
                self._sumo.close(self._api)
        self._running = False

    def close(self) -> None:
        self._broken()
        if self._logs is not None:
            shutil.rmtree(self._logs, ignore_errors=True)
            self._logs = None


def _second(pair: tuple[str, float]) -> float:
    return pair[1]


def _collision_partner(collisions: Any) -> str:
    """The vehicle the ego collided with in this simulation step, or ""."""
    partner = ""
    for collision in collisions:
        if collision.collider == EGO_ID:
            partner = collision.victim
        elif collision.victim == EGO_ID:
            partner = collision.collider
    return partner
