"""The client's reply rules (`agent_client.transport.replies`), one broken rule at a time.

Each case takes a valid reply of the fake backend (one ego, or a frame of three, protocol 1.4),
breaks one rule and expects the `InvalidReply` that names its field; a valid reply passes, and values a newer minor version may
add pass from a server of that version.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import pytest

from agent_client.errors import InvalidReply
from agent_client.transport.replies import ReplyChecker, check_welcome, scenario_problems
from protocol.codec import decode_reply, encode
from protocol.messages import (
    ROAD_RANGE,
    ActionSchema,
    AppliedAction,
    Bye,
    Close,
    Command,
    Conflict,
    EgoObservation,
    Error,
    Events,
    Hello,
    LeaderTrip,
    MultiObservation,
    MultiStep,
    Neighbour,
    Observation,
    Reset,
    Road,
    Route,
    Safety,
    ScenarioInfo,
    Step,
    Traffic,
    Welcome,
)
from protocol.schema import OBSERVATION_FIELDS
from protocol.version import PROTOCOL_VERSION
from sim_server.backends.fake import FAKE_OPTIONS, FakeBackend
from sim_server.session import Session

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
        (
            {"observation_fields": OBSERVATION_FIELDS * 2},
            f"welcome.observation_fields[{len(OBSERVATION_FIELDS)}].name",
        ),
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
    ("stop line behind", lambda o: replace(o, road=Road(ROAD_RANGE, 0, 0.0, 0.0, -3.0)),
     "observation.road.stop_line"),
    ("unknown light", lambda o: replace(
        o, road=Road(ROAD_RANGE, 0, 0.0, 0.0, signal_distance=40.0, signal_state="blue")),
     "observation.road.signal_state"),
    ("light beyond the road", lambda o: replace(
        o, road=Road(ROAD_RANGE, 0, 0.0, 0.0, signal_distance=2000.0, signal_state="red")),
     "observation.road.signal_distance"),
    ("light far in time", lambda o: replace(
        o, road=Road(ROAD_RANGE, 0, 0.0, 0.0, signal_distance=40.0, signal_state="red",
                     signal_switch=500.0)),
     "observation.road.signal_switch"),
    ("a light without a state", lambda o: replace(
        o, road=Road(ROAD_RANGE, 0, 0.0, 0.0, signal_distance=40.0)),
     "observation.road.signal_state"),
    ("collision type unasked", _events(collision_type="junction"),
     "observation.events.collision_type"),
    ("red light reason", lambda o: replace(o, terminated=True, reason="red_light"),
     "observation.reason"),
    ("route running", lambda o: replace(o, route=Route(("a", "b"), 100.0, 1)),
     "observation.route"),
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


def test_signals_red_lights_and_routes_of_1_8_pass() -> None:
    first, after = episode()
    route = Route(("a", "b", "c"), 310.0, 1)
    check = checker(after_reset=False)
    assert check.check(Reset("fake", 1), replace(first, route=route)) is not None
    light = Road(ROAD_RANGE, 0, 0.0, 0.0, 35.0, 35.0, "red", 12.5)
    passed = replace(after, road=light, events=replace(after.events, red_light=True))
    assert check.check(Step(1, 0.5), passed) is not None
    crash = replace(
        after,
        terminated=True,
        reason="red_light",
        events=replace(after.events, red_light=True),
        route=replace(route, driven=2),
    )
    assert checker().check(Step(1, 0.5), crash) is not None
    beyond = replace(crash, route=replace(route, driven=4))
    assert refused(checker(), Step(1, 0.5), beyond).field == "observation.route.driven"


def test_events_stay_false_when_nothing_happened() -> None:
    first, _ = episode()
    assert first.events == Events()


# --------------------------------------------------------------------------- many egos (1.4)

MULTI_RESET = Reset("cf", 1, {"egos": 3})
IDS = ("ego.0", "ego.1", "ego.2")


def multi_step(seq: int = 1, acceleration: float = 0.5, *ids: str) -> MultiStep:
    return MultiStep(seq, tuple(Command(ego, acceleration) for ego in ids or IDS))


def multi_episode() -> tuple[MultiObservation, MultiObservation]:
    """The fake's first frame of three egos and the one after multi_step 1 (all at 0.5)."""
    backend = FakeBackend()
    first = backend.reset_many("cf", 1, {**FAKE_OPTIONS, "egos": 3}, 3)
    return first, backend.step_many(1, {ego: (0.5, 0) for ego in IDS})


def multi_checker() -> ReplyChecker:
    check = ReplyChecker(welcome(), "invalid reply from test")
    check.check(MULTI_RESET, multi_episode()[0])
    return check


FrameBreaker = Callable[[MultiObservation], MultiObservation]


def _one(i: int, breaker: Callable[[EgoObservation], EgoObservation]) -> FrameBreaker:
    """Break ego `i` of a frame."""
    return lambda f: replace(
        f, egos=tuple(breaker(e) if k == i else e for k, e in enumerate(f.egos))
    )


def _ended(i: int, reason: str = "collision", truncated: bool = False) -> FrameBreaker:
    def end(e: EgoObservation) -> EgoObservation:
        if truncated:
            return replace(e, truncated=True, reason=reason)
        events = replace(e.events, collision=True, collision_with="leader")
        return replace(e, terminated=True, reason=reason, events=events)

    return _one(i, end)


def _all(*breakers: FrameBreaker) -> FrameBreaker:
    def apply(f: MultiObservation) -> MultiObservation:
        for breaker in breakers:
            f = breaker(f)
        return f

    return apply


MULTI_CASES: list[tuple[str, FrameBreaker, str]] = [
    ("seq", lambda f: replace(f, seq=2), "multi_observation.seq"),
    ("time", lambda f: replace(f, time=0.0), "multi_observation.time"),
    ("speed", _one(2, lambda e: replace(e, ego=replace(e.ego, speed=-1.0))),
     "multi_observation.egos[2].ego.speed"),
    ("requested", _one(1, lambda e: replace(e, action=replace(e.action, requested_acceleration=0.4))),
     "multi_observation.egos[1].action.requested_acceleration"),
    ("far leader", _one(0, lambda e: replace(e, neighbours=replace(
        e.neighbours, leader=Neighbour(True, 500.0, 0.0, 10.0, "leader")))),
     "multi_observation.egos[0].neighbours.leader.gap"),
    ("collision running", _one(1, lambda e: replace(e, events=replace(
        e.events, collision=True, collision_with="ego.0"))),
     "multi_observation.egos[1].events.collision"),
    ("reason running", _one(2, lambda e: replace(e, reason="collision")),
     "multi_observation.egos[2].reason"),
    ("twice", _one(1, lambda e: replace(e, id="ego.0")), "multi_observation.egos[1].id"),
    ("missing", lambda f: replace(f, egos=f.egos[:2]), "multi_observation.egos"),
    ("stranger", _one(2, lambda e: replace(e, id="ego.7")), "multi_observation.egos"),
    ("order", lambda f: replace(f, egos=f.egos[::-1]), "multi_observation.egos"),
    ("both flags", lambda f: replace(f, terminated=True, truncated=True, reason="time_limit"),
     "multi_observation.truncated"),
    ("terminated early", _all(_ended(0), lambda f: replace(f, terminated=True, reason="collision")),
     "multi_observation.terminated"),
    ("not terminated", _all(_ended(0), _ended(1), _ended(2)), "multi_observation.terminated"),
    ("wrong reason", _all(_ended(0), _ended(1), _ended(2),
                          lambda f: replace(f, terminated=True, reason="stopped")),
     "multi_observation.reason"),
    ("frame reason running", lambda f: replace(f, reason="collision"), "multi_observation.reason"),
    ("one truncated", _ended(1, "time_limit", truncated=True), "multi_observation.truncated"),
    ("not all truncated", _all(_ended(0, "time_limit", truncated=True),
                               lambda f: replace(f, truncated=True, reason="time_limit")),
     "multi_observation.egos[1].truncated"),
    ("truncated reason", _all(_ended(0, "time_limit", True), _ended(1, "time_limit", True),
                              _ended(2, "time_limit", True),
                              lambda f: replace(f, truncated=True, reason="collision")),
     "multi_observation.reason"),
    ("traffic columns", lambda f: replace(
        f, traffic=Traffic(("a",), ("h",), (), (1.0,), (1.0,), (0.0,), ("",), (200.0,), (0.0,))),
     "multi_observation.traffic.lane"),
]  # fmt: skip


@pytest.mark.parametrize(("name", "breaker", "field"), MULTI_CASES, ids=[c[0] for c in MULTI_CASES])
def test_a_broken_multi_step_reply_names_its_field(
    name: str, breaker: FrameBreaker, field: str
) -> None:
    _, after = multi_episode()
    error = refused(multi_checker(), multi_step(), breaker(after))
    assert error.field == field, str(error)
    assert str(error).startswith(f"invalid reply from test: {field}")


def test_a_valid_multi_ego_episode_passes() -> None:
    first, after = multi_episode()
    check = ReplyChecker(welcome())
    assert check.check(MULTI_RESET, first) is first
    assert check.check(multi_step(), after) is after
    assert check.check(multi_step(), after) is after  # a retry: the cached reply
    assert "retry of multi_step 1" in refused(check, multi_step(), replace(after, time=99.0)).rule
    assert check.last_frame is after and set(check.last_egos) == set(IDS)
    assert check.last_egos["ego.1"].seq == 1 and check.last_egos["ego.1"].time == after.time


def test_rules_without_the_previous_frame_take_the_commands_as_the_running_egos() -> None:
    _, after = multi_episode()
    fresh = ReplyChecker(welcome())
    assert fresh.check(multi_step(), after) is after
    error = refused(ReplyChecker(welcome()), multi_step(1, 0.5, "ego.0", "ego.1"), after)
    assert error.field == "multi_observation.egos" and "['ego.0', 'ego.1']" in error.rule


def test_an_ended_ego_is_listed_once_then_no_more() -> None:
    first, after = multi_episode()
    check = ReplyChecker(welcome())
    check.check(MULTI_RESET, first)
    crashed = _ended(0)(after)
    assert check.check(multi_step(), crashed) is crashed
    next_frame = replace(after, seq=2, time=after.time + 0.1)
    again = refused(check, multi_step(2), next_frame)  # lists ego.0 again
    assert again.field == "multi_observation.egos" and "listed once" in again.rule
    without = replace(next_frame, egos=next_frame.egos[1:])
    assert check.check(multi_step(2, 0.5, "ego.1", "ego.2"), without) is without


def test_the_first_frame_has_every_ego_asked_for_and_nothing_decided() -> None:
    first, _ = multi_episode()
    fresh = ReplyChecker(welcome())
    error = refused(fresh, Reset("cf", 1, {"egos": 4}), first)
    assert error.field == "multi_observation.egos" and "4 egos" in error.rule
    teleported = _one(1, lambda e: replace(e, events=replace(e.events, teleported=True)))(first)
    assert refused(fresh, MULTI_RESET, teleported).field == "multi_observation.egos[1].events"
    ended = _ended(0, "time_limit", truncated=True)(first)
    assert refused(fresh, MULTI_RESET, ended).field == "multi_observation.egos[0].truncated"
    over = replace(first, truncated=True, reason="time_limit")
    assert refused(fresh, MULTI_RESET, over).field == "multi_observation.truncated"


def test_each_ego_is_judged_on_its_own_previous_observation() -> None:
    _, after = multi_episode()
    check = multi_checker()
    asked = MultiStep(1, (Command("ego.0", 0.5), Command("ego.1", 0.5, 1), Command("ego.2", 0.5)))
    refusal = _one(1, lambda e: replace(
        e, action=replace(e.action, requested_lane_change=1, lane_change_refused="in_progress"),
        events=replace(e.events, lane_change_refused=True)))(after)  # fmt: skip
    error = refused(check, asked, refusal)
    assert error.field == "multi_observation.egos[1].action.lane_change_refused"
    assert "changing_lane was 0" in error.rule


@pytest.mark.parametrize(
    ("request_", "reply", "words"),
    [
        (MULTI_RESET, episode()[0], "a reset that names egos is answered by multi_observation"),
        (RESET, multi_episode()[0], "a reset is answered by observation"),
        (multi_step(), episode()[1], "a multi_step is answered by multi_observation"),
        (Step(1, 0.5), multi_episode()[1], "a step is answered by observation"),
    ],
)
def test_a_frame_of_the_wrong_kind_is_refused(request_: Any, reply: Any, words: str) -> None:
    error = refused(ReplyChecker(welcome()), request_, reply)
    assert error.field == "reply.type" and words in error.rule


@pytest.mark.parametrize(("default", "words"), [(0, ">= 1"), (1.0, "an int option")])
def test_the_egos_option_is_an_int_of_at_least_one(default: Any, words: str) -> None:
    info = scenario(options={**FAKE_OPTIONS, "egos": default})
    problems = scenario_problems(welcome(scenarios=(info,)))
    assert [p.field for p in problems] == ["welcome.scenarios[0].options.egos"]
    assert words in problems[0].rule


def test_a_hello_forgets_the_multi_ego_episode() -> None:
    check = multi_checker()
    check.check(Hello(PROTOCOL_VERSION), welcome())
    assert check.last_frame is None and check.last_egos == {} and check.last is None


def test_random_multi_ego_episodes_of_the_fake_keep_every_rule() -> None:
    """The fake and the rules agree: random commands, crashes, stops and time limits."""
    rng = random.Random(0)
    session = Session(FakeBackend())

    def ask(request: Any) -> Any:
        return decode_reply(session.handle(b"client", encode(request)))

    check = ReplyChecker(ask(Hello(PROTOCOL_VERSION)))
    reasons: set[str] = set()
    for _ in range(40):
        egos = rng.randint(2, 8)
        options = {"egos": egos, "max_episode_time": rng.choice([2.0, 60.0]), "length": 300.0}
        request: Any = Reset("cf", rng.randrange(2**31), options)
        frame = check.check(request, ask(request))
        assert isinstance(frame, MultiObservation) and len(frame.egos) == egos
        while not (frame.terminated or frame.truncated):
            request = MultiStep(frame.seq + 1, tuple(
                Command(e.id, rng.uniform(-8.0, 5.0), rng.choice((-1, 0, 1)))
                for e in frame.egos if not (e.terminated or e.truncated)
            ))  # fmt: skip
            frame = check.check(request, ask(request))
            assert isinstance(frame, MultiObservation)
            reasons.update(e.reason for e in frame.egos if e.reason)
    assert reasons == {"collision", "stopped", "time_limit", "end_of_road"}


# --------------------------------------------------------------------------- ego_share (1.5)


def joined(frame: MultiObservation, ego_id: str = "human0.7", **changes: Any) -> MultiObservation:
    """`frame` with one more ego appended, as one that joins in it."""
    nothing = {"action": AppliedAction(0.0, 0, 0.0, 0), "events": Events()}
    newcomer = replace(frame.egos[0], id=ego_id, **{**nothing, **changes})
    return replace(frame, egos=(*frame.egos, newcomer))


def share_checker(first: MultiObservation) -> ReplyChecker:
    check = ReplyChecker(welcome(), "invalid reply from test")
    check.check(Reset("cf", 1, {"ego_share": 0.25}), first)
    return check


def test_an_ego_share_episode_lets_new_egos_join_after_the_others() -> None:
    first, after = multi_episode()
    check = share_checker(first)
    assert check.check(multi_step(), joined(after)) is not None
    assert check.seen == {*IDS, "human0.7"}
    reply = joined(after)
    order = replace(reply, egos=(reply.egos[3], *reply.egos[:3]))  # the newcomer first
    assert refused(share_checker(first), multi_step(), order).field == "multi_observation.egos"


def test_only_an_ego_share_episode_has_egos_joining() -> None:
    _, after = multi_episode()
    error = refused(multi_checker(), multi_step(), joined(after))
    assert error.field == "multi_observation.egos"
    assert "exactly the egos driving before the step" in str(error)


def test_an_ego_that_joins_drives() -> None:
    first, after = multi_episode()
    ended = joined(after, terminated=True, reason="stopped")
    error = refused(share_checker(first), multi_step(), ended)
    assert error.field == "multi_observation.egos[3].terminated"


def test_an_ego_that_joins_has_done_nothing_yet() -> None:
    first, after = multi_episode()
    acted = joined(after, action=AppliedAction(0.5, 0, 0.5, 0))
    error = refused(share_checker(first), multi_step(), acted)
    assert error.field == "multi_observation.egos[3].action"
