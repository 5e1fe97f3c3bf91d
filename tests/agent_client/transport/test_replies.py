"""The client's reply rules (`agent_client.transport.replies`), one broken rule at a time.

Each case takes a valid reply of the fake backend, breaks one rule and expects the
`InvalidReply` that names its field; a valid reply passes, and values a newer minor version may
add pass from a server of that version.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import pytest

from agent_client.errors import InvalidReply
from agent_client.transport.replies import ReplyChecker, check_welcome, scenario_problems
from protocol.messages import (
    ActionSchema,
    Bye,
    Close,
    Conflict,
    Error,
    Events,
    Hello,
    LeaderTrip,
    Neighbour,
    Observation,
    Reset,
    Safety,
    ScenarioInfo,
    Step,
    Traffic,
    Welcome,
)
from protocol.schema import OBSERVATION_FIELDS
from protocol.version import PROTOCOL_VERSION
from sim_server.backends.fake import FAKE_OPTIONS, FakeBackend

RESET = Reset("cf", 1)


def welcome(**changes: Any) -> Welcome:
    backend = FakeBackend()
    base = Welcome(
        PROTOCOL_VERSION, "test", backend.name, backend.version, backend.scenarios(),
        OBSERVATION_FIELDS, backend.action_schema, backend.sensor_range, 65536,
    )  # fmt: skip
    return replace(base, **changes)


def episode() -> tuple[Observation, Observation]:
    """The first observation and the one after step 1 (acceleration 0.5)."""
    backend = FakeBackend()
    first = backend.reset("cf", 1, dict(FAKE_OPTIONS))
    return first, backend.step(1, 0.5, 0)


def checker(after_reset: bool = True, **changes: Any) -> ReplyChecker:
    check = ReplyChecker(welcome(**changes), "invalid reply from test")
    if after_reset:
        check.check(RESET, episode()[0])
    return check


def refused(check: ReplyChecker, request: Any, reply: Any) -> InvalidReply:
    with pytest.raises(InvalidReply) as caught:
        check.check(request, reply)
    return caught.value


def test_a_valid_episode_passes() -> None:
    first, after = episode()
    check = ReplyChecker(welcome())
    assert check.check(Hello(PROTOCOL_VERSION), welcome()) is not None
    assert check.check(RESET, first) is first
    assert check.check(Step(1, 0.5), after) is after
    assert check.check(Step(1, 0.5), after) is after  # a retry: the cached reply
    assert check.check(Close(), Bye()) == Bye()


# --------------------------------------------------------------------------- the welcome


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"protocol": (2, 0)}, "welcome.protocol"),
        ({"scenarios": ()}, "welcome.scenarios"),
        ({"observation_fields": ()}, "welcome.observation_fields"),
        ({"observation_fields": OBSERVATION_FIELDS * 2}, "welcome.observation_fields[32].name"),
        ({"action": ActionSchema(1.0, 3.0)}, "welcome.action"),
        ({"action": ActionSchema(-6.0, 3.0, {"left": 1})}, "welcome.action.lane_change"),
        ({"sensor_range": 0.0}, "welcome.sensor_range"),
        ({"max_frame_bytes": 0}, "welcome.max_frame_bytes"),
    ],
)
def test_a_broken_welcome_names_its_field(changes: dict[str, Any], field: str) -> None:
    with pytest.raises(InvalidReply) as caught:
        check_welcome(welcome(**changes))
    assert caught.value.field == field


def scenario(**changes: Any) -> ScenarioInfo:
    return replace(FakeBackend().scenarios()[0], **changes)


@pytest.mark.parametrize(
    ("info", "field", "words"),
    [
        (scenario(step_length=None), "step_length", "required since protocol 1.2"),
        (scenario(step_length=0.0), "step_length", "finite number > 0"),
        (scenario(options={**FAKE_OPTIONS, "max_episode_time": 300}), "max_episode_time",
         "300.0, not 300"),
        (scenario(options={**FAKE_OPTIONS, "report_ceiling": 1}), "report_ceiling", "a bool"),
        (scenario(options={**FAKE_OPTIONS, "decision_interval": 0.15}), "decision_interval",
         "whole number of simulation steps of 0.1 s"),
        (scenario(options={**FAKE_OPTIONS, "decision_interval": -1.0}), "decision_interval",
         "> 0"),
    ],
)  # fmt: skip
def test_a_broken_scenario_names_its_option(info: ScenarioInfo, field: str, words: str) -> None:
    problems = scenario_problems(welcome(scenarios=(info,)))
    assert [p.field.rsplit(".", 1)[-1] for p in problems] == [field]
    assert words in problems[0].rule


def test_only_the_chosen_scenario_is_refused() -> None:
    broken = scenario(name="other", step_length=0.0)
    found, notes = check_welcome(welcome(scenarios=(scenario(), broken)), scenario="cf")
    assert notes == [] and found.scenarios[0].step_length == 0.1
    with pytest.raises(InvalidReply, match=r"scenarios\[1\]\.step_length"):
        check_welcome(welcome(scenarios=(scenario(), broken)))


def test_an_old_server_without_step_length_gets_its_decision_interval() -> None:
    old = welcome(protocol=(1, 1), scenarios=(scenario(step_length=None),))
    found, notes = check_welcome(old)
    assert found.scenarios[0].step_length == 0.1  # the decision_interval default
    assert "assuming 0.1 s" in notes[0]


# --------------------------------------------------------------------------- observations

Breaker = Callable[[Observation], Observation]
ABSENT = Neighbour(False, 200.0, 0.0, 0.0, "")


def _ego(**changes: Any) -> Breaker:
    return lambda o: replace(o, ego=replace(o.ego, **changes))


def _action(**changes: Any) -> Breaker:
    return lambda o: replace(o, action=replace(o.action, **changes))


def _events(**changes: Any) -> Breaker:
    return lambda o: replace(o, events=replace(o.events, **changes))


def _slot(slot: str, neighbour: Neighbour) -> Breaker:
    return lambda o: replace(o, neighbours=replace(o.neighbours, **{slot: neighbour}))


STEP_CASES: list[tuple[str, Breaker, str]] = [
    ("seq", lambda o: replace(o, seq=2), "observation.seq"),
    ("time", lambda o: replace(o, time=0.0), "observation.time"),
    ("both flags", lambda o: replace(o, terminated=True, truncated=True, reason="collision"),
     "observation.truncated"),
    ("reason running", lambda o: replace(o, reason="collision"), "observation.reason"),
    ("unknown reason", lambda o: replace(o, terminated=True, reason="boom"), "observation.reason"),
    ("truncated reason", lambda o: replace(o, truncated=True, reason="collision"),
     "observation.reason"),
    ("negative speed", _ego(speed=-1.0), "observation.ego.speed"),
    ("lane 7", _ego(lane=7), "observation.ego.lane"),
    ("no lanes", _ego(lane_count=0), "observation.ego.lane_count"),
    ("changing 2", _ego(changing_lane=2), "observation.ego.changing_lane"),
    ("no speed limit", _ego(speed_limit=0.0), "observation.ego.speed_limit"),
    ("absent gap", _slot("follower", replace(ABSENT, gap=5.0)), "observation.neighbours.follower.gap"),
    ("far leader", _slot("leader", Neighbour(True, 500.0, 0.0, 10.0, "x")),
     "observation.neighbours.leader.gap"),
    ("left of one lane", _slot("left_leader", Neighbour(True, 10.0, 3.2, 10.0, "x")),
     "observation.neighbours.left_leader.present"),
    ("collision_with", _events(collision_with="x"), "observation.events.collision_with"),
    ("collision running", _events(collision=True, collision_with="x"),
     "observation.events.collision"),
    ("requested", _action(requested_acceleration=0.4), "observation.action.requested_acceleration"),
    ("requested lane", _action(requested_lane_change=1), "observation.action.requested_lane_change"),
    ("beyond bounds", _action(acceleration=4.0), "observation.action.acceleration"),
    ("not as asked", _action(acceleration=0.2), "observation.action.acceleration"),
    ("unknown limit", _action(acceleration_limited_by="wind"),
     "observation.action.acceleration_limited_by"),
    ("lane change 5", _action(lane_change=5), "observation.action.lane_change"),
    ("refusal unasked", _action(lane_change_refused="gap_too_small"),
     "observation.action.lane_change_refused"),
    ("started unapplied", _events(lane_change_started=True),
     "observation.events.lane_change_started"),
    ("ceiling running", lambda o: replace(o, ceiling=LeaderTrip("x", 0.0, 1.0, 10.0)),
     "observation.ceiling"),
    ("safety running", lambda o: replace(o, safety=Safety((), 3.0, 3.0, 2.0)),
     "observation.safety"),
    ("conflict ends first", lambda o: replace(
        o, terminated=True, reason="collision", events=replace(
            o.events, collision=True, collision_with="x"),
        safety=Safety((Conflict("x", 5.0, 4.0, 1.0, 4.0, None, 0.5, 0.1, 0.2),), 3.0, 3.0, 2.0)),
     "observation.safety.conflicts[0].end"),
    ("traffic columns", lambda o: replace(
        o, traffic=Traffic(("a", "b"), ("h", "h"), (0,), (1.0, 2.0), (1.0, 2.0), (0.0, 0.0),
                           ("", ""), (200.0, 200.0), (0.0, 0.0))),
     "observation.traffic.lane"),
]  # fmt: skip


@pytest.mark.parametrize(("name", "breaker", "field"), STEP_CASES, ids=[c[0] for c in STEP_CASES])
def test_a_broken_step_reply_names_its_field(name: str, breaker: Breaker, field: str) -> None:
    _, after = episode()
    error = refused(checker(), Step(1, 0.5), breaker(after))
    assert error.field == field, str(error)
    assert str(error).startswith(f"invalid reply from test: {field}")


def test_a_simulator_driven_ego_may_brake_beyond_the_bounds() -> None:
    _, after = episode()
    human = _action(acceleration=-9.0, acceleration_limited_by="simulator")(after)
    human = _ego(acceleration=-9.0)(human)
    assert checker().check(Step(1, 0.5), human) is human


def test_a_neighbour_rolling_back_is_not_a_broken_reply() -> None:
    """highway-env reports followers at -0.006 m/s after hard braking."""
    _, after = episode()
    rolling = _slot("follower", Neighbour(True, 10.0, 0.0, -0.0065, "h1"))(after)
    assert checker().check(Step(1, 0.5), rolling) is rolling


def test_the_lane_change_is_judged_on_the_lane_it_was_asked_in() -> None:
    first, _ = episode()  # one lane: lane 0 of 1
    backend = FakeBackend()
    backend.reset("cf", 1, dict(FAKE_OPTIONS))
    after = backend.step(1, 0.5, 1)  # refused: no_lane
    assert checker().check(Step(1, 0.5, 1), after) is after
    applied = replace(
        after,
        action=replace(after.action, lane_change=1, lane_change_refused=""),
        events=replace(after.events, lane_change_refused=False, lane_change_started=True),
    )
    error = refused(checker(), Step(1, 0.5, 1), applied)
    assert error.field == "observation.action.lane_change" and "no lane 1" in error.rule
    in_progress = replace(after, action=replace(after.action, lane_change_refused="in_progress"))
    assert "changing_lane was 0" in refused(checker(), Step(1, 0.5, 1), in_progress).rule
    assert first.ego.lane == 0


def test_the_first_observation_is_running_and_has_decided_nothing() -> None:
    first, _ = episode()
    fresh = ReplyChecker(welcome())
    assert refused(fresh, RESET, replace(first, seq=3)).field == "observation.seq"
    assert refused(fresh, RESET, replace(first, truncated=True, reason="time_limit")).field == (
        "observation.truncated"
    )
    assert refused(fresh, RESET, _events(teleported=True)(first)).field == "observation.events"
    assert refused(fresh, RESET, _action(acceleration=1.0)(first)).field == "observation.action"
    old = ReplyChecker(welcome(protocol=(1, 1)))  # a 1.1 server: seq 0 content was open
    assert old.check(RESET, _action(acceleration=1.0)(first)) is not None


def test_a_retry_must_get_the_cached_reply() -> None:
    _, after = episode()
    check = checker()
    check.check(Step(1, 0.5), after)
    assert "retry of step 1" in refused(check, Step(1, 0.5), replace(after, time=99.0)).rule


@pytest.mark.parametrize(
    ("request_", "reply", "field"),
    [
        (Hello(PROTOCOL_VERSION), Bye(), "reply.type"),
        (RESET, welcome(), "reply.type"),
        (Close(), episode()[0], "reply.type"),
        (RESET, Error("oops", "?"), "error.code"),
    ],
)
def test_a_reply_of_the_wrong_kind_is_refused(request_: Any, reply: Any, field: str) -> None:
    assert refused(ReplyChecker(welcome()), request_, reply).field == field


def test_a_newer_minor_server_may_add_values() -> None:
    _, after = episode()
    newer = (PROTOCOL_VERSION[0], PROTOCOL_VERSION[1] + 1)
    check = checker(protocol=newer)
    assert check.check(Close(), Error("new_code", "?")) is not None
    ended = replace(
        after, terminated=True, reason="off_road", action=replace(after.action, acceleration=0.5)
    )
    assert check.check(Step(1, 0.5), _action(acceleration_limited_by="grip")(ended)) is not None
    assert refused(checker(), Step(1, 0.5), ended).field == "observation.reason"


def test_events_stay_false_when_nothing_happened() -> None:
    first, _ = episode()
    assert first.events == Events()
