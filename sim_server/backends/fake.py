"""A tiny kinematic car-following simulator for fast tests: no SUMO, pure Python.

One lane, one leader whose speed follows a seeded random walk, an ego that obeys its acceleration
commands exactly. With the option ``lane_end`` the ego's lane ends before the road does: the road
ahead (protocol 1.6) reports it, and an ego that reaches it stops there (as SUMO stops a vehicle at
the end of a lane that does not lead on) until ``lane_end_patience`` ends the episode. It applies
the same rules as the SUMO backend (`rules`), so server and client logic can be tested in
milliseconds; it never replaces SUMO in integration tests.

Many egos (protocol 1.4, a reset naming ``egos`` > 1): ``ego.0``, ``ego.1``, ... drive in one
column behind the leader, each following the one ahead (`_Column`). Each is judged alone: an ego
that crashes (into the leader, or with the ego ahead of or behind it: both end), reaches the end
of the road or stops is reported once and taken off the road, the others go on; the time limit
truncates every ego still driving. ``egos`` 1 is the one-ego episode, under the id ``ego``.
"""

from __future__ import annotations

import random
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import ClassVar

from protocol.errors import ErrorCode
from protocol.messages import (
    ROAD_RANGE,
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
    Road,
    ScenarioInfo,
)
from sim_server.backends.base import Backend, Commands, ego_part
from sim_server.backends.options import COMMON_OPTIONS, Bounds, EpisodeOptions, ParsedOptions
from sim_server.backends.rules import EndRule, ended, lane_change_refusal, limit_acceleration
from sim_server.errors import BackendError

DT = 0.1
VEHICLE_LENGTH = 5.0
SPEED_LIMIT = 80 / 3.6
MAX_FAKE_EGOS = 32
"""The most egos of a multi-ego episode: enough for any test, and ~32 kB frames at most."""
EGO_SPACING = (20.0, 40.0)
"""Net gaps (m) between consecutive egos at reset, drawn uniformly."""
LEADER_ID = "leader"
FAKE_ROAD = Road(ROAD_RANGE, 0, 0.0, 0.0)
"""The open road of the fake's one lane: no lane beside it."""


@dataclass(frozen=True, slots=True)
class RoadOptions(ParsedOptions):
    """The fake's own option."""

    length: float = 1000.0
    """Metres from the ego's start to the end of the road."""
    lane_end: float = 0.0
    """Metres from the road's start to where the ego's lane ends (0: it does not)."""
    reset_seconds: float = 0.0
    """Wall-clock seconds a reset takes, as a large network's does: for tests of deadlines."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "length": Bounds(0.0, 100_000.0, low_excluded=True),
        "lane_end": Bounds(0.0, 100_000.0),
        "reset_seconds": Bounds(0.0, 60.0),
    }


_SHARED = (
    "decision_interval",
    "max_episode_time",
    "warmup",
    "stop_speed",
    "stop_gap",
    "stop_patience",
    "lane_end_patience",
    "report_ceiling",
    "egos",
)
"""The common options the fake honours (``warmup``: the simulated time at which it starts)."""

FAKE_OPTIONS: dict[str, OptionValue] = {
    **{name: COMMON_OPTIONS[name] for name in _SHARED},
    **RoadOptions().as_options(),
}


@dataclass
class _State:
    time: float
    ego_pos: float
    ego_speed: float
    ego_acc: float
    lead_pos: float
    lead_speed: float
    lead_arrival: float | None
    options: EpisodeOptions
    substeps: int
    length: float
    lane_end: float
    end: EndRule
    rng: random.Random
    done: bool = False


def _road(lane_end: float, position: float) -> Road:
    """The road ahead on the fake's one lane: open, or ending `lane_end` m from the start."""
    if not lane_end:
        return FAKE_ROAD
    return Road(min(ROAD_RANGE, max(0.0, lane_end - position)), 0, 0.0, 0.0)


def _stop_at(lane_end: float, position: float, speed: float) -> tuple[float, float]:
    """An ego that reached the end of its lane stands there."""
    if lane_end and position >= lane_end:
        return lane_end, 0.0
    return position, speed


def _one_lane() -> tuple[int, int]:
    return 0, 1


def _no_gap_check(direction: int) -> bool:
    return True  # never asked: there is no other lane


def ego_ids(count: int) -> tuple[str, ...]:
    """The ids of a multi-ego episode's `count` egos, front first: ``ego.0``, ``ego.1``, ..."""
    return tuple(f"ego.{k}" for k in range(count))


@dataclass
class _Car:
    """One ego of a multi-ego episode."""

    id: str
    pos: float
    speed: float
    end: EndRule
    """Its own end rule (its own stop timer; the entry time is the episode's)."""
    acc: float = 0.0


@dataclass
class _Drive:
    """One ego's decision being simulated: the command, and what was applied so far."""

    request: float
    lane_change: int
    applied: list[float] = field(default_factory=list)
    limited_by: str = ""


class _Column:
    """The egos of a multi-ego episode on the fake's one lane, front first, behind the leader.

    Each ego's leader is the ego ahead of it (the first ego's is the leader), its follower the
    ego behind it. Egos start at one speed, 20-40 m apart, so that egos commanded alike keep
    their gaps; the leader's speed follows the one-ego fake's random walk.
    """

    def __init__(
        self, ids: tuple[str, ...], seed: int, options: dict[str, OptionValue], backend: Backend
    ) -> None:
        episode = EpisodeOptions.parse(options)
        road = RoadOptions.parse(options)
        self.length, self.lane_end = road.length, road.lane_end
        self.rng = rng = random.Random(seed)
        self.sensor_range = backend.sensor_range
        self.low = backend.action_schema.acceleration_min
        self.high = backend.action_schema.acceleration_max
        self.substeps = episode.steps_per_decision(DT)
        self.time = episode.warmup
        speed = rng.uniform(10.0, 18.0)
        positions = [VEHICLE_LENGTH]  # from the last ego, at the start of the road, forward
        for _ in ids[1:]:
            positions.append(positions[-1] + VEHICLE_LENGTH + rng.uniform(*EGO_SPACING))
        if positions[-1] >= self.length:
            raise BackendError(
                ErrorCode.INVALID_OPTION,
                f"option length {self.length:g} m is too short for {len(ids)} egos: the first "
                f"would start {positions[-1]:.0f} m along the road",
            )
        self.cars = [
            _Car(ego_id, position, speed, EndRule(episode, entry_time=episode.warmup))
            for ego_id, position in zip(ids, reversed(positions), strict=True)
        ]
        self.lead_pos = positions[-1] + rng.uniform(20.0, 60.0) + VEHICLE_LENGTH
        self.lead_speed = speed + rng.uniform(-2.0, 2.0)
        self.done = False

    def first(self) -> MultiObservation:
        """Every ego at seq 0: nothing happened, nothing decided."""
        nothing = AppliedAction(0.0, 0, 0.0, 0)
        observations = [self._observe(0, i, Events(), nothing) for i in range(len(self.cars))]
        return self._report(0, observations)

    def step(self, seq: int, commands: Commands) -> MultiObservation:
        """Every running ego's decision (the session checked the ids), then each judged."""
        drives = {car.id: _Drive(*commands[car.id]) for car in self.cars}
        self._drive(drives)
        partners = self._collisions()
        observations = []
        for i, car in enumerate(self.cars):
            drive = drives[car.id]
            refused = lane_change_refusal(
                drive.lane_change,
                simulator_drives=False,
                under_way=None,
                ego_lane=_one_lane,
                gap_ok=_no_gap_check,
            )
            partner = partners.get(car.id, "")
            events = Events(
                collision=bool(partner),
                collision_with=partner,
                end_of_road=not partner and car.pos >= self.length,
                lane_change_refused=bool(refused),
            )
            mean = sum(drive.applied) / len(drive.applied)
            action = AppliedAction(
                drive.request, drive.lane_change, mean, 0, drive.limited_by, refused
            )
            obs = self._observe(seq, i, events, action)
            reason = car.end.check(obs)
            observations.append(obs if reason is None else ended(obs, reason))
        return self._report(seq, observations)

    def _drive(self, drives: dict[str, _Drive]) -> None:
        """Move the egos and the leader through one decision."""
        for _ in range(self.substeps):
            for car in self.cars:
                drive = drives[car.id]
                acc, why = limit_acceleration(
                    drive.request, car.speed, SPEED_LIMIT, self.low, self.high, DT
                )
                drive.applied.append(acc)
                drive.limited_by = drive.limited_by or why
                car.pos += car.speed * DT + 0.5 * acc * DT * DT
                car.speed = max(0.0, car.speed + acc * DT)  # standstill: -speed / DT, exactly 0
                car.acc = acc
                car.pos, car.speed = _stop_at(self.lane_end, car.pos, car.speed)
            self.lead_speed = min(SPEED_LIMIT, max(0.0, self.lead_speed + self.rng.gauss(0, 0.3)))
            self.lead_pos += self.lead_speed * DT
            self.time = round(self.time + DT, 6)

    def _ahead(self, i: int) -> tuple[float, float, str]:
        """Position, speed and id of the vehicle ahead of ego `i`: the ego ahead, or the leader."""
        if i == 0:
            return self.lead_pos, self.lead_speed, LEADER_ID
        ahead = self.cars[i - 1]
        return ahead.pos, ahead.speed, ahead.id

    def _collisions(self) -> dict[str, str]:
        """Every ego that overlaps the vehicle ahead of or behind it -> that vehicle's id (two
        egos that collide end both)."""
        partners: dict[str, str] = {}
        for i, car in enumerate(self.cars):
            position, _, other = self._ahead(i)
            if position - VEHICLE_LENGTH - car.pos < 0:
                partners[car.id] = other
                if i > 0:
                    partners[other] = car.id
        return partners

    def _observe(self, seq: int, i: int, events: Events, action: AppliedAction) -> Observation:
        car = self.cars[i]
        absent = Neighbour(False, self.sensor_range, 0.0, 0.0)
        position, speed, other = self._ahead(i)
        gap = position - VEHICLE_LENGTH - car.pos
        leader = Neighbour(True, gap, 0.0, speed, other) if gap <= self.sensor_range else absent
        follower = absent
        if i + 1 < len(self.cars):
            behind = self.cars[i + 1]
            gap = car.pos - VEHICLE_LENGTH - behind.pos
            if gap <= self.sensor_range:
                follower = Neighbour(True, gap, 0.0, behind.speed, behind.id)
        return Observation(
            seq=seq,
            time=self.time,
            ego=Ego(car.speed, car.acc, 0, 1, car.pos, SPEED_LIMIT),
            neighbours=Neighbours(absent, absent, leader, follower, absent, absent),
            events=events,
            action=action,
            road=_road(self.lane_end, car.pos),
        )

    def _report(self, seq: int, observations: list[Observation]) -> MultiObservation:
        """The frame of every ego that drove into this step; the ended ones leave the road.

        Truncated when the time limit came (it truncates every ego still driving); terminated
        when no ego is left, with the reason of the last one listed that ended."""
        egos = tuple(
            ego_part(car.id, obs) for car, obs in zip(self.cars, observations, strict=True)
        )
        self.cars = [car for car, e in zip(self.cars, egos, strict=True) if not _over(e)]
        if any(e.truncated for e in egos):
            self.done = True
            return MultiObservation(seq, self.time, egos, False, True, EndReason.TIME_LIMIT)
        if not self.cars:
            self.done = True
            return MultiObservation(seq, self.time, egos, True, False, egos[-1].reason)
        return MultiObservation(seq, self.time, egos)


def _over(ego: EgoObservation) -> bool:
    return ego.terminated or ego.truncated


class FakeBackend(Backend):
    """Deterministic single-lane follower dynamics (scenario ``cf``)."""

    name = "fake"

    @property
    def version(self) -> str:
        return "1"

    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        return (ScenarioInfo("cf", "kinematic single-lane car following", dict(FAKE_OPTIONS), DT),)

    max_egos = MAX_FAKE_EGOS

    def __init__(self) -> None:
        self._state: _State | None = None
        self._column: _Column | None = None
        """The running multi-ego episode (``egos`` > 1), or None."""

    def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
        self._column = None
        episode = EpisodeOptions.parse(options)
        road = RoadOptions.parse(options)
        if road.reset_seconds:
            time.sleep(road.reset_seconds)
        rng = random.Random(seed)
        speed = rng.uniform(10.0, 18.0)
        self._state = _State(
            time=episode.warmup,
            ego_pos=VEHICLE_LENGTH,
            ego_speed=speed,
            ego_acc=0.0,
            lead_pos=VEHICLE_LENGTH + rng.uniform(20.0, 60.0) + VEHICLE_LENGTH,
            lead_speed=speed + rng.uniform(-2.0, 2.0),
            lead_arrival=None,
            options=episode,
            substeps=episode.steps_per_decision(DT),
            length=road.length,
            lane_end=road.lane_end,
            end=EndRule(episode, entry_time=episode.warmup),
            rng=rng,
        )
        return self._observe(0, Events(), AppliedAction(0.0, 0, 0.0, 0))

    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        state = self._state
        if state is None or state.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        limited_by = self._drive(state, acceleration)
        refused = lane_change_refusal(
            lane_change,
            simulator_drives=False,
            under_way=None,
            ego_lane=_one_lane,
            gap_ok=_no_gap_check,
        )
        gap = state.lead_pos - VEHICLE_LENGTH - state.ego_pos
        events = Events(
            collision=gap < 0,
            collision_with="leader" if gap < 0 else "",
            end_of_road=gap >= 0 and state.ego_pos >= state.length,
            lane_change_refused=bool(refused),
        )
        action = AppliedAction(acceleration, lane_change, state.ego_acc, 0, limited_by, refused)
        obs = self._observe(seq, events, action)
        reason = state.end.check(obs)
        if reason is None:
            return obs
        state.done = True
        obs = ended(obs, reason)
        return (
            replace(obs, ceiling=self._leader_trip(state)) if state.options.report_ceiling else obs
        )

    def reset_many(
        self, scenario: str, seed: int, options: dict[str, OptionValue], egos: int
    ) -> MultiObservation:
        """``egos`` 1: the one-ego episode under the id ``ego`` (as every one-ego backend serves
        it); more: a column of egos (`_Column`)."""
        if egos == 1 or egos > self.max_egos:
            return super().reset_many(scenario, seed, options, egos)  # or its refusal
        column = _Column(ego_ids(egos), seed, options, self)  # a refusal changes nothing
        self._state, self._column = None, column
        return column.first()

    def step_many(self, seq: int, commands: Commands) -> MultiObservation:
        column = self._column
        if column is None:
            return super().step_many(seq, commands)  # a one-ego episode
        if column.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        return column.step(seq, commands)

    def _drive(self, state: _State, request: float) -> str:
        """Move both vehicles through one decision; what limited the ego's acceleration."""
        low, high = self.action_schema.acceleration_min, self.action_schema.acceleration_max
        limited_by = ""
        for _ in range(state.substeps):
            acc, why = limit_acceleration(request, state.ego_speed, SPEED_LIMIT, low, high, DT)
            limited_by = limited_by or why
            state.ego_pos += state.ego_speed * DT + 0.5 * acc * DT * DT
            state.ego_speed = max(0.0, state.ego_speed + acc * DT)  # standstill: exactly 0
            state.ego_acc = acc
            state.ego_pos, state.ego_speed = _stop_at(
                state.lane_end, state.ego_pos, state.ego_speed
            )
            state.lead_speed = min(
                SPEED_LIMIT, max(0.0, state.lead_speed + state.rng.gauss(0, 0.3))
            )
            state.lead_pos += state.lead_speed * DT
            state.time = round(state.time + DT, 6)
            if state.lead_arrival is None and state.lead_pos >= state.length:
                state.lead_arrival = state.time
        return limited_by

    @staticmethod
    def _leader_trip(state: _State) -> LeaderTrip:
        """Run the leader on to the end of the road; it entered when the ego did."""
        while state.lead_arrival is None:
            state.lead_pos += max(state.lead_speed, 1.0) * DT
            state.time += DT
            if state.lead_pos >= state.length:
                state.lead_arrival = state.time
        entry = state.options.warmup
        average = (state.length - 10.0) / (state.lead_arrival - entry)
        return LeaderTrip("leader", entry, state.lead_arrival, average)

    def _observe(self, seq: int, events: Events, action: AppliedAction) -> Observation:
        state = self._state
        assert state is not None
        absent = Neighbour(False, self.sensor_range, 0.0, 0.0)
        gap = state.lead_pos - VEHICLE_LENGTH - state.ego_pos
        leader = (
            Neighbour(True, gap, 0.0, state.lead_speed, "leader")
            if gap <= self.sensor_range
            else absent
        )
        return Observation(
            seq=seq,
            time=state.time,
            ego=Ego(state.ego_speed, state.ego_acc, 0, 1, state.ego_pos, SPEED_LIMIT),
            neighbours=Neighbours(absent, absent, leader, absent, absent, absent),
            events=events,
            action=action,
            road=_road(state.lane_end, state.ego_pos),
        )

    def close(self) -> None:
        self._state = None
        self._column = None
