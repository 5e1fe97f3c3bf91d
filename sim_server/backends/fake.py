"""A tiny kinematic car-following simulator for fast tests: no SUMO, pure Python.

One lane, one leader whose speed follows a seeded random walk, an ego that obeys its acceleration
commands exactly. It applies the same rules as the SUMO backend (`rules`), so server and client
logic can be tested in milliseconds; it never replaces SUMO in integration tests.
"""

from __future__ import annotations

import random
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import ClassVar

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
from sim_server.backends.base import Backend
from sim_server.backends.options import COMMON_OPTIONS, Bounds, EpisodeOptions, ParsedOptions
from sim_server.backends.rules import EndRule, ended, lane_change_refusal, limit_acceleration
from sim_server.errors import BackendError

DT = 0.1
VEHICLE_LENGTH = 5.0
SPEED_LIMIT = 80 / 3.6


@dataclass(frozen=True, slots=True)
class RoadOptions(ParsedOptions):
    """The fake's own option."""

    length: float = 1000.0
    """Metres from the ego's start to the end of the road."""

    BOUNDS: ClassVar[Mapping[str, Bounds]] = {
        "length": Bounds(0.0, 100_000.0, low_excluded=True),
    }


_SHARED = (
    "decision_interval",
    "max_episode_time",
    "warmup",
    "stop_speed",
    "stop_gap",
    "stop_patience",
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
    end: EndRule
    rng: random.Random
    done: bool = False


def _one_lane() -> tuple[int, int]:
    return 0, 1


def _no_gap_check(direction: int) -> bool:
    return True  # never asked: there is no other lane


class FakeBackend(Backend):
    """Deterministic single-lane follower dynamics (scenario ``cf``)."""

    name = "fake"

    @property
    def version(self) -> str:
        return "1"

    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        return (ScenarioInfo("cf", "kinematic single-lane car following", dict(FAKE_OPTIONS), DT),)

    def __init__(self) -> None:
        self._state: _State | None = None

    def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
        episode = EpisodeOptions.parse(options)
        length = RoadOptions.parse(options).length
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
            length=length,
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

    def _drive(self, state: _State, request: float) -> str:
        """Move both vehicles through one decision; what limited the ego's acceleration."""
        low, high = self.action_schema.acceleration_min, self.action_schema.acceleration_max
        limited_by = ""
        for _ in range(state.substeps):
            acc, why = limit_acceleration(request, state.ego_speed, SPEED_LIMIT, low, high, DT)
            limited_by = limited_by or why
            state.ego_pos += state.ego_speed * DT + 0.5 * acc * DT * DT
            state.ego_speed += acc * DT
            state.ego_acc = acc
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
        )

    def close(self) -> None:
        self._state = None
