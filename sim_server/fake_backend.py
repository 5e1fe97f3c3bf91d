"""A tiny kinematic car-following simulator for fast tests: no SUMO, pure Python.

One lane, one leader whose speed follows a seeded random walk, an ego that obeys its acceleration
commands exactly. It speaks the same observations and termination rules as the SUMO backend, so
server and client logic can be tested in milliseconds; it never replaces SUMO in integration
tests.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, replace

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
from sim_server.scenarios import check_options

DT = 0.1
VEHICLE_LENGTH = 5.0
SPEED_LIMIT = 80 / 3.6

FAKE_OPTIONS: dict[str, OptionValue] = {
    "decision_interval": 0.1,
    "max_episode_time": 300.0,
    "length": 1000.0,
    "stop_speed": 1.0,
    "stop_gap": 15.0,
    "stop_patience": 2.0,
    "report_ceiling": True,
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
    options: dict[str, OptionValue]
    rng: random.Random
    stopped_since: float | None = None
    done: bool = False


class FakeBackend(Backend):
    """Deterministic single-lane follower dynamics (scenario ``cf``)."""

    name = "fake"

    @property
    def version(self) -> str:
        return "1"

    def scenarios(self) -> tuple[ScenarioInfo, ...]:
        return (ScenarioInfo("cf", "kinematic single-lane car following", dict(FAKE_OPTIONS)),)

    def __init__(self) -> None:
        self._state: _State | None = None

    def reset(self, scenario: str, seed: int, options: dict[str, OptionValue]) -> Observation:
        check_options(options)
        for name in ("decision_interval", "max_episode_time", "length"):
            if not float(options[name]) > 0:  # type: ignore[arg-type]
                raise BackendError(ErrorCode.INVALID_OPTION, f"option {name} must be > 0")
        rng = random.Random(seed)
        speed = rng.uniform(10.0, 18.0)
        self._state = _State(
            time=30.0,
            ego_pos=VEHICLE_LENGTH,
            ego_speed=speed,
            ego_acc=0.0,
            lead_pos=VEHICLE_LENGTH + rng.uniform(20.0, 60.0) + VEHICLE_LENGTH,
            lead_speed=speed + rng.uniform(-2.0, 2.0),
            lead_arrival=None,
            options=options,
            rng=rng,
        )
        return self._observe(0, Events(), AppliedAction(0.0, 0, 0.0, 0))

    def step(self, seq: int, acceleration: float, lane_change: int) -> Observation:
        state = self._state
        if state is None or state.done:
            raise BackendError(ErrorCode.OUT_OF_ORDER, "no running episode: send reset first")
        substeps = max(1, round(float(state.options["decision_interval"]) / DT))  # type: ignore[arg-type]
        length = float(state.options["length"])  # type: ignore[arg-type]
        low, high = self.action_schema.acceleration_min, self.action_schema.acceleration_max
        applied, limited_by = min(max(acceleration, low), high), ""
        if applied != acceleration:
            limited_by = "bounds"
        events = Events(lane_change_refused=lane_change != 0)
        for _ in range(substeps):
            acc = applied
            if state.ego_speed + acc * DT > SPEED_LIMIT:
                acc, limited_by = (SPEED_LIMIT - state.ego_speed) / DT, "speed_limit"
            if state.ego_speed + acc * DT < 0:
                acc, limited_by = -state.ego_speed / DT, "standstill"
            state.ego_pos += state.ego_speed * DT + 0.5 * acc * DT * DT
            state.ego_speed += acc * DT
            state.ego_acc = acc
            state.lead_speed = min(
                SPEED_LIMIT, max(0.0, state.lead_speed + state.rng.gauss(0, 0.3))
            )
            state.lead_pos += state.lead_speed * DT
            state.time = round(state.time + DT, 6)
            if state.lead_arrival is None and state.lead_pos >= length:
                state.lead_arrival = state.time
        gap = state.lead_pos - VEHICLE_LENGTH - state.ego_pos
        action = AppliedAction(
            acceleration,
            lane_change,
            state.ego_acc,
            0,
            limited_by,
            "no_lane" if lane_change else "",
        )
        if gap < 0:
            events = Events(
                collision=True, collision_with="leader", lane_change_refused=lane_change != 0
            )
        elif state.ego_pos >= length:
            events = Events(end_of_road=True, lane_change_refused=lane_change != 0)
        obs = self._observe(seq, events, action)
        reason = self._termination(state, obs, gap)
        if not reason:
            return obs
        state.done = True
        truncated = reason == "time_limit"
        ceiling = None
        if state.options["report_ceiling"]:
            while state.lead_arrival is None:
                state.lead_pos += max(state.lead_speed, 1.0) * DT
                state.time += DT
                if state.lead_pos >= length:
                    state.lead_arrival = state.time
            average = (length - 10.0) / (state.lead_arrival - 30.0)
            ceiling = LeaderTrip("leader", 30.0, state.lead_arrival, average)
        return replace(
            obs, terminated=not truncated, truncated=truncated, reason=reason, ceiling=ceiling
        )

    def _termination(self, state: _State, obs: Observation, gap: float) -> str:
        if obs.events.collision:
            return "collision"
        if obs.events.end_of_road:
            return "end_of_road"
        slow = state.ego_speed < float(state.options["stop_speed"])  # type: ignore[arg-type]
        far = gap > float(state.options["stop_gap"]) and state.ego_speed < state.lead_speed  # type: ignore[arg-type]
        if slow and far:
            state.stopped_since = (
                state.stopped_since if state.stopped_since is not None else state.time
            )
            if state.time - state.stopped_since >= float(state.options["stop_patience"]) - 1e-9:  # type: ignore[arg-type]
                return "stopped"
        else:
            state.stopped_since = None
        if state.time - 30.0 >= float(state.options["max_episode_time"]) - 1e-9:  # type: ignore[arg-type]
            return "time_limit"
        return ""

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
