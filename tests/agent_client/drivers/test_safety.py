"""The safety layer: it overrides a learned driver only where a stated rule says the drive is at
stake (a collision, a red light, a lane end about to be missed), and the episode counts it."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from agent_client.drivers.episode import Episode
from agent_client.drivers.safety import EMERGENCY_DECELERATION, NONE, Override, SafetyLayer
from agent_client.evaluation.metrics import episode_summary
from protocol.messages import ROAD_RANGE, Ego, Events, Neighbour, Neighbours, Road
from tests.protocol.test_codec import make_observation

ABSENT = Neighbour(False, 200.0, 0.0, 0.0)
LAYER = SafetyLayer(interval=0.1, lowest=-6.0)


def observation(
    speed: float,
    leader: Neighbour = ABSENT,
    road: Road | None = None,
    lane: int = 0,
    lanes: int = 1,
):  # type: ignore[no-untyped-def]
    return make_observation(
        seq=5,
        ego=Ego(speed, 0.0, lane, lanes, 300.0, 22.22),
        neighbours=Neighbours(ABSENT, ABSENT, leader, ABSENT, ABSENT, ABSENT),
        road=road,
        events=Events(),
    )


def test_following_at_a_safe_distance_is_left_to_the_policy() -> None:
    calm = observation(20.0, Neighbour(True, 25.0, 0.0, 20.0, "car"))
    assert LAYER.apply(calm, 1.0, 0) == (1.0, 0, NONE)
    assert LAYER.apply(observation(20.0), 3.0, 0) == (3.0, 0, NONE)  # nobody ahead


def test_closing_in_on_a_standing_vehicle_the_layer_brakes() -> None:
    """25 m/s towards a car standing 54 m ahead: at the policy's +1 m/s² it could no longer stop
    (52.5 m of braking at 6 m/s² after 2.5 m of the decision, 1 m to spare); the layer brakes
    just enough."""
    obs = observation(25.0, Neighbour(True, 54.0, 0.0, 0.0, "stopped"))
    acceleration, lane, override = LAYER.apply(obs, 1.0, 0)
    assert override == Override(acceleration=True, lane_change=False, rule="collision")
    assert -EMERGENCY_DECELERATION <= acceleration < 1.0 and lane == 0
    assert LAYER._collision_free(obs) == pytest.approx(acceleration)
    softer = LAYER.apply(obs, acceleration - 0.5, 0)
    assert softer[2] == NONE  # braking harder than needed is the policy's own choice


def test_a_red_light_it_can_still_stop_for_is_not_run() -> None:
    """20 m/s, a red light 35 m ahead: stopping takes 5.9 m/s² now, more than the ego has after
    one more decision at +2 m/s²; the layer brakes (and no harder than the ego can)."""
    red = Road(ROAD_RANGE, 0, 0.0, 0.0, stop_line=35.0, signal_distance=35.0, signal_state="red")
    acceleration, _, override = LAYER.apply(observation(20.0, road=red), 2.0, 0)
    assert override.rule == "stop_line" and -EMERGENCY_DECELERATION <= acceleration < 0.0
    assert LAYER.apply(observation(20.0, road=red), acceleration, 0)[2] == NONE
    far = replace(red, stop_line=200.0, signal_distance=200.0)
    assert LAYER.apply(observation(20.0, road=far), 2.0, 0)[2] == NONE  # not at stake yet
    too_late = replace(red, stop_line=8.0, signal_distance=8.0)
    assert LAYER.apply(observation(20.0, road=too_late), 2.0, 0)[2] == NONE  # braking cannot help


def crossing_time(speed: float, line: float, left: float, brake: float, layer: bool) -> float:
    """Seconds until the ego's front is across a yellow light's line `line` m ahead (turning
    red in `left` s), the policy braking at `brake` m/s² throughout, through the layer or
    not; inf where it stops first."""
    t, dt = 0.0, 0.1
    for _ in range(200):
        if line <= 0.0:
            return t
        if speed <= 0.0:
            return math.inf
        road = Road(ROAD_RANGE, 0, 0.0, 0.0, signal_distance=line, signal_state="yellow",
                    signal_switch=max(left - t, 0.0))  # fmt: skip
        a = LAYER.apply(observation(speed, road=road), brake, 0)[0] if layer else brake
        v_next = max(speed + a * dt, 0.0)
        line -= 0.5 * (speed + v_next) * dt
        speed, t = v_next, t + dt
    return math.inf


def test_a_yellow_light_braked_for_too_late_is_cleared_before_it_turns_red() -> None:
    """20 m/s, a yellow light 29 m ahead turning red in 1.9 s (the shipped roads policy on an
    OSM city): it cannot stop (6.9 m/s² needed), and braking at 5.5 m/s² it reached the line
    after the light had turned red. The layer lets it brake while it still makes the line in
    time at the speed it has, then holds it there; braking that can stop stays the policy's."""
    assert crossing_time(20.05, 29.0, 1.9, -5.5, layer=False) > 1.9  # red when it crosses
    assert crossing_time(20.05, 29.0, 1.9, -5.5, layer=True) <= 1.9 + 1e-6  # 1 m past by then
    yellow = Road(ROAD_RANGE, 0, 0.0, 0.0, signal_distance=29.0, signal_state="yellow",
                  signal_switch=1.9)  # fmt: skip
    assert LAYER.apply(observation(20.05, road=yellow), -5.5, 0)[2] == NONE  # still makes it
    late = replace(yellow, signal_distance=29.0 - 0.1 * 20.0, signal_switch=1.4)
    acceleration, _, override = LAYER.apply(observation(19.0, road=late), -5.5, 0)
    assert override.rule == "yellow" and acceleration > -5.5
    early = replace(yellow, signal_distance=45.0, signal_switch=2.8)  # 22 m/s: it can stop
    assert LAYER.apply(observation(22.0, road=early), -5.0, 0)[2] == NONE
    far = replace(yellow, signal_distance=36.0, signal_switch=1.3)  # too far to clear in time
    acceleration, _, override = LAYER.apply(observation(20.0, road=far), 2.0, 0)
    assert override.rule == "yellow" and 1.0 < acceleration < 2.0  # it keeps the stop possible
    v_next = 20.0 + 0.1 * acceleration
    assert v_next**2 / (2 * EMERGENCY_DECELERATION) <= 36.0 - 0.05 * (20.0 + v_next) + 1e-6


def test_a_lane_end_about_to_be_missed_gets_the_change_the_route_needs() -> None:
    merging = Road(30.0, 1, ROAD_RANGE, 0.0)
    obs = observation(15.0, road=merging, lane=0, lanes=3)
    _, lane, override = LAYER.apply(obs, 0.0, 0)
    assert lane == 1 and override.lane_change and override.rule == "lane_end"
    assert LAYER.apply(obs, 0.0, 1)[2] == replace(NONE)  # the policy asked: nothing to do
    early = replace(merging, lane_end=300.0)
    assert LAYER.apply(observation(15.0, road=early, lanes=3), 0.0, 0)[2] == NONE
    changing = replace(obs, ego=replace(obs.ego, changing_lane=1))
    assert not LAYER.apply(changing, 0.0, 0)[2].lane_change  # a change is under way


@pytest.mark.parametrize(("right_lane_end", "refused"), [(110.0, True), (200.0, False)])
def test_a_change_into_a_lane_that_ends_about_now_is_not_made(
    right_lane_end: float, refused: bool
) -> None:
    """At 33 m/s in a lane that leads on, beside an acceleration lane ending 110 m ahead (less
    than 4 s at its speed): a change right is kept from being made, counted; one 200 m before
    its end, and one to the left, are the policy's to make."""
    beside = Road(ROAD_RANGE, 0, ROAD_RANGE, right_lane_end)
    obs = observation(33.0, road=beside, lane=1, lanes=3)
    _, lane, override = LAYER.apply(obs, 0.0, -1)
    assert (lane, override.lane_change, override.rule) == (
        (0, True, "lane_end") if refused else (-1, False, "")
    )
    assert LAYER.apply(obs, 0.0, 1)[1:] == (1, NONE)


def test_the_episode_counts_the_layers_decisions() -> None:
    first = observation(10.0)
    moved = replace(first, seq=6, time=first.time + 0.1)
    started = replace(moved, seq=7, time=moved.time + 0.1, events=Events(lane_change_started=True))
    episode = Episode(step_length=0.1)
    for obs in (first, moved, started):
        episode.add(obs)
    episode.overrides = [Override(True, False, "collision"), Override(False, True, "lane_end")]
    summary = episode_summary(episode)
    assert summary.safety_steps == 2 and summary.safety_lane_changes == 1
    assert episode_summary(replace(episode, overrides=[NONE, NONE])).safety_steps == 0
    assert math.isclose(summary.steps, 2)


def test_a_stop_nothing_calls_for_is_ended_by_moving_off() -> None:
    standing = observation(0.2)
    acceleration, _, override = LAYER.apply(standing, -1.0, 0)
    assert override.rule == "standstill" and acceleration >= 1.0
    queued = observation(0.2, Neighbour(True, 6.0, 0.0, 0.0, "queue"))
    assert LAYER.apply(queued, -1.0, 0)[2] == NONE  # a queue: waiting is right
    at_red = Road(ROAD_RANGE, 0, 0.0, 0.0, stop_line=3.0, signal_distance=3.0, signal_state="red")
    assert LAYER.apply(observation(0.2, road=at_red), -1.0, 0)[2].rule != "standstill"
    assert LAYER.apply(standing, 1.5, 0)[2] == NONE  # it moves off itself
    # The servers' rule (protocol §6) decides what a needless stop is, not a distance of its own:
    going = observation(0.2, Neighbour(True, 18.0, 0.0, 5.0, "away"))
    assert LAYER.apply(going, -1.0, 0)[2].rule == "standstill"  # its leader drives away
    slower = observation(0.2, Neighbour(True, 18.0, 0.0, 0.0, "standing"))
    assert LAYER.apply(slower, -1.0, 0)[2] == NONE
    far_red = Road(
        ROAD_RANGE, 0, 0.0, 0.0, stop_line=18.0, signal_distance=18.0, signal_state="red"
    )
    acceleration, _, override = LAYER.apply(observation(0.2, road=far_red), -1.0, 0)
    assert override.rule == "standstill" and 0.0 < acceleration <= 1.0  # closer, not through
    gap_wait = Road(100.0, 1, 100.0, ROAD_RANGE)  # a lane to reach 100 m ahead: waits for a gap
    assert LAYER.apply(observation(0.2, road=gap_wait, lanes=2), -1.0, 0)[2] == NONE
