"""`HighwayBackend`: highway-env behind the bridge, and its episode loop.

A reset builds the scenario's scene (`Scenario.build`), lets highway-env's human model drive the
egos through the ``warmup`` and hands them over to the client (`ClientVehicle`: highway-env's
lateral controller, the client's acceleration); a step runs the decision's simulation steps
(`simulation.advance`) with the request limited anew on each, and judges the ego after each. An
episode that ends with ``report_ceiling`` runs on without the ego until the leader-at-entry
arrives (`_leader_trip`). A reset naming ``egos`` > 1 drives several egos (`many.py`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import highway_env

from protocol.errors import ErrorCode
from protocol.messages import (
    AccelerationLimit,
    AppliedAction,
    EndReason,
    Events,
    LeaderTrip,
    MultiObservation,
    Observation,
    OptionValue,
    ScenarioInfo,
)
from sim_server.backends.base import Backend, Commands
from sim_server.backends.highway.egos import ClientVehicle, Driven, Episode
from sim_server.backends.highway.lane_changes import (
    lane_change_progress,
    refusal,
    start_lane_change,
)
from sim_server.backends.highway.many import decide, first_frame
from sim_server.backends.highway.observation import Observer
from sim_server.backends.highway.scenarios import SCENARIOS, Scenario
from sim_server.backends.highway.scene import DT, SIMULATION_FREQUENCY
from sim_server.backends.highway.simulation import (
    advance,
    around,
    collided_with,
    outcome,
    stranded,
)
from sim_server.backends.options import EpisodeOptions
from sim_server.backends.rules import EndRule, ended, limit_acceleration
from sim_server.errors import BackendError

EGO_ID = "ego"
MAX_HIGHWAY_EGOS = 16
"""The most egos of one episode (``controlled_vehicles``); highway-env's cost is O(N²) per step
in the vehicles on the road."""
CEILING_HORIZON = 3600.0
"""Longest extra simulated time (s) spent waiting for the leader-at-entry to arrive."""
CEILING_MIN_SPEED = 5.0
"""m/s: the slowest average speed the leader-at-entry is waited for over its remaining road."""
SIMULATOR_DRIVERS = ("simulator", "sumo")
"""Values of ``ego_driver`` that let highway-env's human model drive the ego."""


class HighwayBackend(Backend):
    """highway-env scenes advanced with ``road.act()`` / ``road.step(dt)``; see the package
    doc (`sim_server.backends.highway`)."""

    name = "highway"
    max_egos = MAX_HIGHWAY_EGOS

    def __init__(self) -> None:
        self._episode: Episode | None = None
        self._observer = Observer(self.sensor_range)

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
        substeps = episode_options.steps_per_decision(DT)
        self._episode = None
        episode = self._build(chosen, seed, options, episode_options, substeps)
        self._start(episode)
        leader, _ = around(episode, episode.ego, episode.ego.lane_index, own=True)
        if leader is not None and episode.layout.drives_route(leader):  # else it bounds nothing
            episode.leader = leader
        self._episode = episode
        return self._observe(episode, 0, Events(), AppliedAction(0.0, 0, 0.0, 0))

    def _build(
        self,
        scenario: Scenario,
        seed: int,
        options: Mapping[str, OptionValue],
        episode_options: EpisodeOptions,
        substeps: int,
        names: tuple[str, ...] = (EGO_ID,),
    ) -> Episode:
        """The scenario's road and vehicles (`Scenario.build`), egos named `names`; a human
        placed beyond the end of its road never enters it, an ego placed there or past the end of
        its lane is refused."""
        scene = scenario.build(seed, options, names)
        road, layout = scene.road, scene.layout
        fleet: list[Driven] = [] if names == (EGO_ID,) else [
            Driven(name, vehicle, EndRule(episode_options, 0.0))
            for name, vehicle in zip(names, scene.egos, strict=True)
        ]  # fmt: skip
        episode = Episode(
            scenario=scenario,
            road=road,
            layout=layout,
            ego=None if fleet else scene.egos[0],
            options=episode_options,
            substeps=substeps,
            ids=scene.ids,
            spawn_front={},
            fleet=fleet,
        )
        egos = dict(zip(scene.egos, names, strict=True))
        for vehicle in list(road.vehicles):
            front = layout.along(vehicle)
            beyond = front >= layout.end_of(vehicle.lane_index[:2])
            if vehicle in egos and (beyond or layout.past_lane_end(vehicle)):
                what = "the ego" if not fleet else egos[vehicle]
                raise BackendError(
                    ErrorCode.INVALID_OPTION,
                    f"vehicles_behind and vehicles_density place {what} beyond the end of "
                    "the road; fewer vehicles behind it or a higher density"
                    + ("" if not fleet else ", or fewer egos"),
                )
            if beyond:  # placed beyond the end: never on the road
                road.vehicles.remove(vehicle)
            episode.spawn_front[vehicle] = front
        return episode

    def _start(self, episode: Episode) -> None:
        """The warm-up, then the hand-over to the client (or highway-env's human model drives on,
        changing lanes from then on); the episode's time runs from there."""
        self._warm_up(episode)
        if episode.options.simulator_drives:
            for ego in episode.egos():
                ego.enable_lane_change = True
        else:
            self._hand_over(episode)
        episode.end = EndRule(episode.options, entry_time=episode.time)
        for driven in episode.fleet:
            driven.end = EndRule(episode.options, entry_time=episode.time)

    def _warm_up(self, episode: Episode) -> None:
        """highway-env's human model drives the ego for ``warmup`` seconds."""
        warmup = episode.options.warmup
        layout = episode.layout
        names = {d.vehicle: d.id for d in episode.fleet}
        for _ in range(math.ceil(warmup * SIMULATION_FREQUENCY - 1e-9)):
            advance(episode)
            for ego in episode.egos():
                if ego.crashed:
                    what = names.get(ego, "the ego")
                    raise BackendError(
                        ErrorCode.INSERTION_FAILED,
                        f"{what} crashed during the warm-up (driven by highway-env); try "
                        "another seed",
                    )
        for ego in episode.egos():
            what = names.get(ego, "the ego")
            reached = ""
            if layout.past_lane_end(ego):
                reached = "drove past the end of its lane"
            elif layout.along(ego) >= layout.length:
                reached = "reached the end of the road"
            if reached:
                raise BackendError(
                    ErrorCode.INVALID_OPTION,
                    f"warmup {warmup} s: {what} {reached} before the client took over",
                )

    @classmethod
    def _hand_over(cls, episode: Episode) -> None:
        """Replace the ego's human model by the client's control, in the same list slot."""
        if not episode.fleet:
            episode.ego = cls._take_over(episode, episode.ego)
        for driven in episode.fleet:
            driven.vehicle = cls._take_over(episode, driven.vehicle)

    @staticmethod
    def _take_over(episode: Episode, human: Any) -> Any:
        """The client's vehicle in `human`'s place (list slot, id, spawn position)."""
        ego = ClientVehicle.create_from(human)
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
            refusal(episode, episode.ego, episode.lane_change, lane_change) if lane_change else ""
        )
        started = bool(lane_change) and not refused
        if started:
            episode.lane_change = start_lane_change(episode, episode.ego, lane_change)
        action, events, lane_end = self._drive(episode, acceleration, lane_change, refused, started)
        obs = self._observe(episode, seq, events, action)
        reason = EndReason.LANE_END if lane_end else episode.end.check(obs)
        if reason is None:
            return obs
        episode.done = True
        obs = ended(obs, reason)
        if episode.options.report_ceiling:
            obs = replace(obs, ceiling=self._leader_trip(episode))
        return obs

    def _drive(
        self, episode: Episode, request: float, lane_change: int, refused: str, started: bool
    ) -> tuple[AppliedAction, Events, bool]:
        """Run the decision's simulation steps, the request limited anew on each (bounds, the
        speed limit of the ego's lane, standstill); stop early at a crash, the end of the road or
        the end of the ego's lane (the flag returned: the episode then ends with ``lane_end``)."""
        ego, drives = episode.ego, episode.options.simulator_drives
        low, high = self.action_schema.acceleration_min, self.action_schema.acceleration_max
        applied_total, limited_by = 0.0, ""
        collision_with, ending, completed, aborted = "", "", False, False
        done = 0
        for _ in range(episode.substeps):
            why: str = AccelerationLimit.SIMULATOR
            if not drives:
                limit = float(ego.lane.speed_limit)
                ego.command, why = limit_acceleration(
                    request, float(ego.speed), limit, low, high, DT
                )
            advance(episode)
            if not drives and ego.speed < 0.0:
                ego.speed = 0.0  # rounding of -v/dt * dt; the protocol's speed is >= 0
            applied_total += float(ego.action["acceleration"])
            limited_by = limited_by or why
            done += 1
            ending = outcome(episode, ego)
            if ending == EndReason.COLLISION:
                episode.collided = collided_with(episode, ego)
                collision_with = episode.ids.get(episode.collided, "unknown")
            if ending:
                break
            if episode.lane_change is not None:
                completed, aborted = lane_change_progress(episode, ego, episode.lane_change)
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
            end_of_road=ending == EndReason.END_OF_ROAD,
            lane_change_started=started,
            lane_change_completed=completed,
            lane_change_refused=bool(refused),
            lane_change_aborted=aborted,
        )
        return action, events, ending == EndReason.LANE_END

    def _observe(
        self, episode: Episode, seq: int, events: Events, action: AppliedAction
    ) -> Observation:
        """The one ego's observation."""
        return self._observer.observe(
            episode, episode.ego, episode.lane_change, seq, events, action
        )

    def _leader_trip(self, episode: Episode) -> LeaderTrip | None:
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
            layout = episode.layout
            mine = layout.along(leader)
            road.vehicles = [v for v in road.vehicles if layout.along(v) >= mine]
            # As SUMO's server: the time its remaining road takes at CEILING_MIN_SPEED, and a
            # minute (a leader that leaves by a ramp never arrives where the ego does).
            remaining = max(0.0, layout.length - mine)
            horizon = min(CEILING_HORIZON, 60.0 + remaining / CEILING_MIN_SPEED)
            end = episode.steps + round(horizon * SIMULATION_FREQUENCY)
            while episode.leader_arrival is None and episode.steps < end:
                if leader.crashed or stranded(episode, leader):
                    break  # highway-env stops it for good: it never arrives
                advance(episode)
        arrival = episode.leader_arrival
        name = episode.ids[leader]
        if arrival is None:
            return LeaderTrip(name, 0.0, None, None)
        average = (episode.leader_end - episode.spawn_front[leader]) / arrival
        return LeaderTrip(name, arrival - episode.layout.length / average, arrival, average)

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
        substeps = episode_options.steps_per_decision(DT)
        names = tuple(f"ego.{k}" for k in range(egos))
        self._episode = None
        episode = self._build(chosen, seed, options, episode_options, substeps, names)
        self._start(episode)
        self._episode = episode
        return first_frame(episode, self._observer)

    def step_many(self, seq: int, commands: Commands) -> MultiObservation:
        episode = self._episode
        if episode is not None and not episode.fleet:
            return super().step_many(seq, commands)  # a one-ego episode (egos 1)
        if episode is None or episode.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        return decide(episode, seq, commands, self._observer, self.action_schema)

    # ----------------------------------------------------------------------- lifecycle

    def close(self) -> None:
        self._episode = None
