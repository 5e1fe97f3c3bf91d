from __future__ import annotations

import dataclasses
import math
from dataclasses import replace
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent_client.rl.rewards import (
    REWARDS,
    LaneChangeReward,
    NormalisedReward,
    RewardFn,
    SafeReward,
    flags,
    gap_readiness,
    jerk,
    make_reward,
    max_reward,
    q_upper_bound,
    route_potential,
)
from protocol.messages import (
    OPEN_ROAD,
    ROAD_RANGE,
    AppliedAction,
    Ego,
    Events,
    Neighbour,
    Neighbours,
    Observation,
    Road,
)

DT = 0.1
LIMIT = 80 / 3.6
ABSENT = Neighbour(False, 200.0, 0.0, 0.0)


def kmh(v: float) -> float:
    return v / 3.6


def lead(gap: float, speed: float, vid: str = "lead") -> Neighbour:
    return Neighbour(True, gap, 0.0, speed, vid)


def make_obs(
    speed: float = 20.0,
    acceleration: float = 0.0,
    time: float = 1.0,
    *,
    leader: Neighbour = ABSENT,
    follower: Neighbour = ABSENT,
    left_follower: Neighbour = ABSENT,
    right_follower: Neighbour = ABSENT,
    speed_limit: float = LIMIT,
    events: Events | None = None,
    lane_change: int = 0,
    refused: str = "",
) -> Observation:
    """An observation with the fields the rewards read; everything else neutral."""
    neighbours = Neighbours(ABSENT, left_follower, leader, follower, ABSENT, right_follower)
    action = AppliedAction(acceleration, lane_change, acceleration, lane_change, "", refused)
    return Observation(
        seq=round(time / DT),
        time=time,
        ego=Ego(speed, acceleration, 1, 3, 100.0, speed_limit),
        neighbours=neighbours,
        events=events or Events(),
        action=action,
    )


def pair(prev_acc: float, acc: float, **kwargs: Any) -> tuple[Observation, Observation]:
    """Two observations DT apart whose acceleration changes from prev_acc to acc."""
    prev = make_obs(acceleration=prev_acc, time=1.0, **kwargs)
    return prev, make_obs(acceleration=acc, time=1.0 + DT, **kwargs)


FOLLOWING: dict[str, Any] = {"leader": lead(30.0, 20.0)}


# --------------------------------------------------------------------------- flags


def test_flags_otherwise() -> None:
    f = flags(None, make_obs(**FOLLOWING), DT)
    assert f.otherwise
    assert f.letters() == "O"


def test_collision_by_event_and_by_negative_gap() -> None:
    assert flags(None, make_obs(events=Events(collision=True)), DT).collision
    assert flags(None, make_obs(leader=lead(-0.2, 20.0)), DT).letters() == "C"
    assert not flags(None, make_obs(leader=lead(0.0, 20.0)), DT).collision


def test_reverse() -> None:
    assert flags(None, make_obs(speed=-0.1, leader=lead(5.0, 0.0)), DT).reverse


def test_uncomfortable_jerk() -> None:
    prev, obs = pair(0.0, 0.6)  # 6 m/s^3
    assert jerk(prev, obs, DT) == pytest.approx(6.0)
    assert flags(prev, obs, DT).uncomfortable
    prev, obs = pair(0.0, -0.6)
    assert flags(prev, obs, DT).uncomfortable
    prev, obs = pair(0.0, 0.5)  # 5 m/s^3
    assert not flags(prev, obs, DT).uncomfortable
    assert not flags(None, obs, DT).uncomfortable  # no prev, no jerk


def test_jerk_uses_elapsed_time_not_dt() -> None:
    prev = make_obs(acceleration=0.0, time=1.0)
    obs = make_obs(acceleration=1.0, time=2.0)  # 1 m/s^3 over a 1 s decision
    assert jerk(prev, obs, DT) == pytest.approx(1.0)


def test_low_speed_flag() -> None:
    assert flags(None, make_obs(speed=0.5, leader=lead(20.0, 5.0)), DT).letters() == "L"
    assert not flags(None, make_obs(speed=0.5, leader=lead(10.0, 5.0)), DT).low_speed  # near
    assert not flags(None, make_obs(speed=0.5, leader=lead(20.0, 0.0)), DT).low_speed  # faster
    assert not flags(None, make_obs(speed=1.5, leader=lead(20.0, 5.0)), DT).low_speed
    assert flags(None, make_obs(speed=0.5), DT).low_speed  # no leader: crawling is L
    assert not flags(None, make_obs(speed=5.0), DT).low_speed


def test_gap_too_small_flag() -> None:
    assert flags(None, make_obs(refused="gap_too_small"), DT).letters() == "G"
    assert not flags(None, make_obs(refused="no_lane"), DT).gap_too_small


# --------------------------------------------------------------------------- paper rewards


def test_ra3_cases() -> None:
    ra3 = make_reward("ra3")
    assert ra3(None, make_obs(events=Events(collision=True)), DT) == -1.0
    assert ra3(None, make_obs(speed=-0.1, leader=lead(5.0, 0.0)), DT) == -1.0
    assert ra3(*pair(0.0, 0.6, **FOLLOWING), DT) == -0.8
    assert ra3(None, make_obs(speed=0.5, leader=lead(20.0, 5.0)), DT) == -0.5
    normal = make_obs(speed=kmh(60.0), leader=lead(30.0, kmh(60.0)))
    assert ra3(None, normal, DT) == pytest.approx(0.75 - 0.3)


def test_ra3_without_leader_is_the_faithful_pitfall() -> None:
    ra3 = make_reward("ra3")
    free = make_obs(speed=LIMIT)  # d = 200 m sensor range: 1 - 2
    assert ra3(None, free, DT) == pytest.approx(-1.0)
    assert make_reward("ra3", no_leader_gap=0.0)(None, free, DT) == pytest.approx(1.0)


def test_ra4_is_100_times_ra3() -> None:
    ra3, ra4 = make_reward("ra3"), make_reward("ra4")
    cases = [
        (None, make_obs(events=Events(collision=True))),
        pair(0.0, 0.6, **FOLLOWING),
        (None, make_obs(speed=0.5, leader=lead(20.0, 5.0))),
        (None, make_obs(speed=kmh(60.0), leader=lead(30.0, kmh(60.0)))),
    ]
    for prev, obs in cases:
        assert ra4(prev, obs, DT) == pytest.approx(100.0 * ra3(prev, obs, DT))


def test_ra1() -> None:
    ra1 = make_reward("ra1")
    assert ra1(None, make_obs(speed=20.0, leader=lead(30.0, 15.0)), DT) == pytest.approx(10.0)
    assert ra1(None, make_obs(events=Events(collision=True)), DT) == -100.0
    assert ra1(*pair(0.0, 0.6, **FOLLOWING), DT) == -80.0
    assert ra1(None, make_obs(speed=0.5, leader=lead(20.0, 5.0)), DT) == -50.0


def test_ra2() -> None:
    ra2 = make_reward("ra2")
    # v = 72 km/h; d - h_d v = 30 - 40 = -10 m; dv' = 5 m/s * 3.6 / 40 = 0.45 -> 72 / 4.5
    assert ra2(None, make_obs(speed=20.0, leader=lead(30.0, 15.0)), DT) == pytest.approx(16.0)
    # at d = h_d v the denominator is floored at epsilon
    assert ra2(None, make_obs(speed=20.0, leader=lead(40.0, 15.0)), DT) == pytest.approx(72e3)
    assert ra2(None, make_obs(events=Events(collision=True)), DT) == -100.0


# --------------------------------------------------------------------------- rlc


def lane_change_pair(
    follower_after: float = 19.9, target_after: float = 17.8, target_id: str = "f2"
) -> tuple[Observation, Observation]:
    """A left lane change: f1 behind in the source lane, f2 behind in the target lane."""
    prev = make_obs(
        speed=kmh(60.0),
        acceleration=0.5,
        time=1.0,
        leader=lead(40.0, 17.0),
        follower=lead(20.0, 20.0, "f1"),
        left_follower=lead(15.0, 18.0, "f2"),
    )
    obs = make_obs(  # after the change f2 is behind the ego, f1 behind on the right
        speed=kmh(60.0),
        acceleration=1.0,
        time=1.0 + DT,
        leader=lead(40.0, 17.0),
        follower=lead(15.0, target_after, target_id),
        right_follower=lead(20.0, follower_after, "f1"),
        events=Events(lane_change_started=True),
        lane_change=1,
    )
    return prev, obs


def test_rlc_car_following_and_penalties() -> None:
    rlc = make_reward("rlc")
    assert rlc(None, make_obs(speed=kmh(60.0), leader=lead(30.0, 15.0)), DT) == pytest.approx(0.75)
    assert rlc(None, make_obs(refused="gap_too_small"), DT) == -0.8
    assert rlc(*pair(0.0, 0.6, **FOLLOWING), DT) == -0.8
    assert rlc(None, make_obs(events=Events(collision=True)), DT) == -1.0
    assert rlc(None, make_obs(speed=0.5, leader=lead(20.0, 5.0)), DT) == -0.5


def test_rlc_lane_change_step() -> None:
    prev, obs = lane_change_pair()
    # |da| = 0.5, f1: -0.1 m/s over 0.1 s = -1, f2: -0.2 m/s over 0.1 s = -2
    assert LaneChangeReward.disturbance(prev, obs, DT) == pytest.approx(3.5)
    assert make_reward("rlc")(prev, obs, DT) == pytest.approx(2 * 0.75 - 0.1 * 3.5)


def test_rlc_braking_follower_costs_and_unknown_follower_counts_zero() -> None:
    rlc = make_reward("rlc")
    calm = rlc(*lane_change_pair(follower_after=20.0, target_after=18.0), DT)
    assert calm == pytest.approx(1.5 - 0.05)
    assert rlc(*lane_change_pair(follower_after=19.5), DT) < calm  # f1 brakes at 5 m/s^2
    assert rlc(*lane_change_pair(follower_after=20.5), DT) < calm  # magnitudes: any change costs
    swapped = lane_change_pair(follower_after=20.0, target_after=10.0, target_id="other")
    assert rlc(*swapped, DT) == pytest.approx(calm)  # identity changed: 0


# --------------------------------------------------------------------------- safe


def safe_at(speed: float, headway: float | None, **kwargs: Any) -> float:
    leader = lead(headway * speed, speed) if headway is not None else ABSENT
    return SafeReward()(None, make_obs(speed=speed, leader=leader, **kwargs), DT)


def test_safe_is_the_default() -> None:
    assert isinstance(make_reward(), SafeReward)


def test_safe_collision_penalty_beats_worst_collision_free_future() -> None:
    safe = SafeReward()
    assert safe(None, make_obs(events=Events(collision=True)), DT) == -20.0
    assert safe.worst_step() == pytest.approx(-0.1)
    assert safe.min_collision_penalty(0.99) == pytest.approx(11.0)  # missing the route: 5 + 3 x 2
    assert safe.collision_penalty > safe.min_collision_penalty(0.99)


def discounted(rewards: list[float], gamma: float = 0.99) -> float:
    return sum(r * gamma**t for t, r in enumerate(rewards))


def drive(
    reward: RewardFn, throttle: float, steps: int = 600, gap: float = 30.0, v_lead: float = 15.0
) -> list[float]:
    """Rewards of a hand-made run behind a 15 m/s leader; the episode ends on a collision."""
    speed, acc, time, out = v_lead, 0.0, 0.0, []
    prev = make_obs(speed=speed, time=time, leader=lead(gap, v_lead))
    for _ in range(steps):
        acc = throttle if speed < LIMIT else 0.0
        speed = min(speed + acc * DT, LIMIT)
        gap += (v_lead - speed) * DT
        time += DT
        crashed = gap < 0.0
        obs = make_obs(
            speed=speed,
            acceleration=acc,
            time=time,
            leader=lead(gap, v_lead),
            events=Events(collision=crashed),
        )
        out.append(reward(prev, obs, DT))
        if crashed:
            break
        prev = obs
    return out


def test_safe_full_throttle_crash_is_worse_than_following() -> None:
    safe, ra3 = SafeReward(), NormalisedReward()
    crash, follow = drive(safe, 3.0), drive(safe, 0.0)
    assert len(crash) == 54 and crash[-1] == -20.0 and len(follow) == 600
    assert discounted(crash) == pytest.approx(6.4, abs=0.1)
    assert discounted(follow) == pytest.approx(67.3, abs=0.1)
    assert discounted(crash) < 0.1 * discounted(follow)
    # the docstring's comparison: under r_a3 the crash run earns most of the follower's return
    ra3_crash, ra3_follow = discounted(drive(ra3, 3.0)), discounted(drive(ra3, 0.0))
    assert ra3_crash == pytest.approx(26.9, abs=0.1)
    assert ra3_follow == pytest.approx(37.4, abs=0.1)


def test_safe_tailgating_pays_less_than_safe_following() -> None:
    for speed in (5.0, 15.0, LIMIT):
        assert safe_at(speed, 0.5) < safe_at(speed, 1.0) < safe_at(speed, 1.5)
    assert safe_at(15.0, 1.5) == pytest.approx(15.0 / LIMIT)
    assert safe_at(15.0, 0.5) < 0.1 * safe_at(15.0, 1.5)


def test_safe_headway_knee_sits_between_the_safety_line_and_idm() -> None:
    # exp(-ln(h / 1.2)^2 / (2 * 0.3^2)), by hand: h = 1.0 -> 0.8314, 0.8 -> 0.4012, 0.5 -> 0.0142
    expected = {1.5: 1.0, 1.2: 1.0, 1.0: 0.8314, 0.8: 0.4012, 0.5: 0.0142}
    for headway, score in expected.items():
        assert safe_at(15.0, headway) == pytest.approx(15.0 / LIMIT * score, abs=1e-4)


def test_safe_no_leader_scores_like_good_free_driving() -> None:
    free = safe_at(LIMIT, None)
    assert free == pytest.approx(1.0)
    assert free >= safe_at(LIMIT, 1.5)
    assert safe_at(LIMIT, 8.0) == pytest.approx(free)  # a far leader is like an empty road
    assert safe_at(0.0, None) == 0.0 > -20.0
    assert safe_at(LIMIT + 2.0, None) == pytest.approx(1.0)  # speeding never pays


def test_safe_far_sigma_pays_for_closing_up_to_the_knee() -> None:
    far = SafeReward(headway_far_sigma=1.0)

    def at(headway: float) -> float:
        return far(None, make_obs(speed=15.0, leader=lead(headway * 15.0, 15.0)), DT)

    assert at(1.2) == pytest.approx(15.0 / LIMIT)  # the peak stays at the knee
    # exp(-ln(h / 1.2)^2 / 2), by hand: h = 1.5 -> 0.9754, 3.0 -> 0.6572
    assert at(1.5) == pytest.approx(15.0 / LIMIT * 0.9754, abs=1e-4)
    assert at(3.0) == pytest.approx(15.0 / LIMIT * 0.6572, abs=1e-4)
    assert at(1.0) == pytest.approx(safe_at(15.0, 1.0))  # below the knee: unchanged


def test_safe_far_weight_bounds_what_a_far_leader_costs() -> None:
    bounded = SafeReward(headway_far_sigma=0.5, headway_far_weight=0.2)

    def at(headway: float) -> float:
        return bounded(None, make_obs(speed=15.0, leader=lead(headway * 15.0, 15.0)), DT)

    drive = 15.0 / LIMIT
    assert at(1.2) == pytest.approx(drive)  # the peak stays at the knee
    # 1 - 0.2 (1 - exp(-ln(h / 1.2)^2 / 0.5)), by hand: h = 2.0 -> 0.9187, 3.0 -> 0.8373
    assert at(2.0) == pytest.approx(drive * 0.9187, abs=1e-4)
    assert at(3.0) == pytest.approx(drive * 0.8373, abs=1e-4)
    assert at(1.5) > at(2.0) > at(3.0) > at(12.0) >= 0.8 * drive  # closer pays, never below 0.8
    assert at(1.0) == pytest.approx(safe_at(15.0, 1.0))  # below the knee: unchanged
    no_leader = bounded(None, make_obs(speed=15.0), DT)
    assert no_leader == pytest.approx(drive)  # an empty road is still the best there is
    with pytest.raises(ValueError, match="headway_far_weight"):
        SafeReward(headway_far_weight=1.5)
    flat = SafeReward(headway_far_weight=0.2)  # sigma_far inf: the weight changes nothing
    assert flat(None, make_obs(speed=15.0, leader=lead(45.0, 15.0)), DT) == safe_at(15.0, 3.0)
    plain = SafeReward(headway_far_sigma=1.0)  # weight 1: the log-normal, bit for bit
    for h in (1.3, 2.0, 7.5):
        obs = make_obs(speed=15.0, leader=lead(h * 15.0, 15.0))
        ratio = math.log((h * 15.0 / 15.0) / 1.2)
        assert plain.headway_score(obs) == math.exp(-(ratio**2) / 2.0)


def test_safe_stop_penalty_makes_an_unreasonable_stop_a_failure() -> None:
    standing = make_obs(speed=0.5)
    stopped = dataclasses.replace(standing, terminated=True, reason="stopped")
    arrived = dataclasses.replace(standing, terminated=True, reason="end_of_road")
    default, strict = SafeReward(), SafeReward(stop_penalty=20.0)
    assert default(None, stopped, DT) == default(None, standing, DT) > 0.0  # 0: as before
    assert strict(None, stopped, DT) == -20.0
    assert strict(None, arrived, DT) == strict(None, standing, DT)  # only that end costs
    crash_and_stop = dataclasses.replace(stopped, events=Events(collision=True), reason="collision")
    assert strict(None, crash_and_stop, DT) == -20.0  # a crash is a crash
    assert strict.min_collision_penalty(0.99) == 20.0  # the stop sets the bound now
    with pytest.raises(ValueError, match="penalties and route weight must be non-negative"):
        SafeReward(stop_penalty=-1.0)
    with pytest.raises(ValueError, match="must not exceed collision_penalty"):
        SafeReward(stop_penalty=30.0)


def test_safe_ttc_penalty() -> None:
    safe = SafeReward()
    closing = make_obs(speed=20.0, leader=lead(40.0, 10.0))  # h = 2 s, TTC = 4 s
    assert safe(None, closing, DT) == pytest.approx(20.0 / LIMIT)
    half = make_obs(speed=20.0, leader=lead(40.0, 0.0))  # TTC = 2 s: half the drive term
    assert safe(None, half, DT) == pytest.approx(0.5 * 20.0 / LIMIT)
    ttc_1s = make_obs(speed=20.0, leader=lead(40.0, -20.0))
    assert safe(None, ttc_1s, DT) < safe(None, half, DT)


def test_safe_jerk_gate_is_smooth_and_proportional() -> None:
    base = safe_at(15.0, 2.0)

    def with_jerk(j: float) -> float:
        return SafeReward()(*pair(0.0, j * DT, leader=lead(30.0, 15.0), speed=15.0), DT)

    assert with_jerk(1.0) == pytest.approx(base * (1 - 0.5 / 5.6**2))  # small jerk, small cost
    assert with_jerk(5.6) == pytest.approx(base * 0.5)  # half the drive term at the threshold
    assert with_jerk(5.5) - with_jerk(5.7) < 0.02 * base  # no cliff at the threshold
    assert with_jerk(50.0) == pytest.approx(base * 0.5)  # capped
    assert with_jerk(50.0) >= 0.0  # never below ending the episode


def test_safe_lane_change_costs() -> None:
    base = safe_at(15.0, 2.0)
    assert base - safe_at(15.0, 2.0, refused="gap_too_small") == pytest.approx(0.1)
    assert base - safe_at(15.0, 2.0, refused="no_lane") == pytest.approx(0.1)  # asking in vain
    assert base - safe_at(15.0, 2.0, refused="in_progress") == pytest.approx(0.1)
    assert base - safe_at(15.0, 2.0, refused="simulator_drives") == pytest.approx(0.0)
    started = safe_at(15.0, 2.0, events=Events(lane_change_started=True), lane_change=1)
    assert base - started == pytest.approx(0.01)
    custom = SafeReward(refused_weight=0.3)(None, make_obs(speed=15.0, refused="gap_too_small"), DT)
    assert custom == pytest.approx(15.0 / LIMIT - 0.3)


def test_safe_rejects_bad_weights() -> None:
    with pytest.raises(ValueError, match="ttc_weight"):
        SafeReward(ttc_weight=2.0)
    with pytest.raises(ValueError, match="jerk_weight"):
        SafeReward(jerk_weight=-1.0)
    with pytest.raises(ValueError, match="non-negative"):
        SafeReward(collision_penalty=-1.0)


# --------------------------------------------------------------------------- registry, bounds


def test_registry_and_unknown_name() -> None:
    assert set(REWARDS) == {"ra1", "ra2", "ra3", "ra4", "rlc", "safe", "wave", "wave_own"}
    with pytest.raises(ValueError, match="ra1, ra2, ra3, ra4, rlc, safe, wave, wave_own"):
        make_reward("nope")
    assert make_reward("ra1", desired_headway=1.0)(
        None, make_obs(speed=20.0, leader=lead(30.0, 15.0)), DT
    ) == pytest.approx(-10.0)


def test_max_reward_and_q_upper_bound() -> None:
    assert max_reward("ra3") == pytest.approx(1 - 2 * LIMIT / 100)
    assert max_reward("ra3") == pytest.approx(0.56, abs=0.005)
    assert q_upper_bound("ra3", 0.99) == pytest.approx(56.0, abs=0.5)
    assert q_upper_bound("ra4", 0.99) == pytest.approx(5556, abs=1)
    assert max_reward("ra1") == pytest.approx(0.0)
    assert max_reward("ra2") == pytest.approx(80e3)
    assert max_reward("rlc") == pytest.approx(1.0)
    assert q_upper_bound("safe", 0.99) == pytest.approx(100.0)
    assert q_upper_bound(0.5, 0.9) == pytest.approx(5.0)
    with pytest.raises(ValueError, match="gamma"):
        q_upper_bound(1.0, 1.0)


neighbours = st.builds(
    Neighbour,
    present=st.booleans(),
    gap=st.floats(-10.0, 300.0),
    lateral=st.floats(-10.0, 10.0),
    speed=st.floats(0.0, 70.0),
    id=st.sampled_from(["", "a", "b"]),
)
observations = st.builds(
    make_obs,
    speed=st.floats(-1.0, 70.0),
    acceleration=st.floats(-10.0, 10.0),
    time=st.floats(0.0, 1000.0),
    leader=neighbours,
    follower=neighbours,
    left_follower=neighbours,
    right_follower=neighbours,
    speed_limit=st.floats(0.0, 40.0),
    events=st.builds(
        Events,
        collision=st.booleans(),
        lane_change_started=st.booleans(),
    ),
    lane_change=st.sampled_from([-1, 0, 1]),
    refused=st.sampled_from(["", "gap_too_small", "no_lane", "in_progress"]),
)


@settings(max_examples=300, deadline=None)
@given(prev=st.none() | observations, obs=observations, dt=st.floats(0.0, 2.0))
def test_all_rewards_finite_and_bounded(
    prev: Observation | None, obs: Observation, dt: float
) -> None:
    # wave and wave_own read the traffic, which these lack (test_rewards_wave.py has its own)
    values = {
        name: make_reward(name)(prev, obs, dt) for name in REWARDS if not name.startswith("wave")
    }
    assert all(math.isfinite(v) for v in values.values()), values
    safe = values["safe"]
    assert safe == -20.0 or -0.1 - 1e-12 <= safe <= 1.0
    if not (obs.events.collision or obs.ego.speed < 0.0 or obs.neighbours.leader.gap < 0.0):
        assert safe >= -0.1 - 1e-12
    assert values["ra4"] == pytest.approx(100.0 * values["ra3"])
    assert values["ra3"] >= -1.0 - 310.0 / 100.0
    assert values["ra3"] <= 70.0 * 3.6 / 80.0 + 0.1


# --------------------------------------------------------------------------- the route


def on_road(road: Road, speed: float = 20.0, reason: str = "") -> Observation:
    return replace(make_obs(speed=speed), road=road, reason=reason, terminated=bool(reason))


def test_a_lane_change_towards_the_route_earns_what_staying_would_cost() -> None:
    safe = SafeReward()
    before = on_road(Road(200.0, 1, ROAD_RANGE, 0.0))
    changed = on_road(Road(ROAD_RANGE, 0, 0.0, 190.0))
    stayed = on_road(Road(198.0, 1, ROAD_RANGE, 0.0))
    # the same drive term: the difference is the potential's, w (0 - (-(1 - 198 / 1000))) with
    # the lane beside empty, an open gap: half the lane's weight already off
    assert safe(before, changed, DT) - safe(before, stayed, DT) == pytest.approx(2.0 * 0.401)
    assert route_potential(before) == pytest.approx(-0.4)
    assert route_potential(changed) == 0.0
    assert safe(before, stayed, DT) < safe(before, before, DT) + 1e-9  # drawing near costs


def test_opening_a_gap_beside_pays_before_the_change() -> None:
    merging = Road(100.0, 1, ROAD_RANGE, 0.0)
    beside = replace(make_obs(speed=20.0), road=merging)
    blocked = replace(
        beside,
        neighbours=replace(beside.neighbours, left_leader=Neighbour(True, 2.5, 3.2, 20.0, "l")),
    )  # 20 m short of the secure 22.5 m: the gap counts as closed
    assert gap_readiness(blocked, 1) == 0.0 and gap_readiness(beside, 1) == 1.0
    assert route_potential(beside) - route_potential(blocked) == pytest.approx(0.9 * 0.5)


def test_the_route_shaping_sums_to_the_potentials_difference() -> None:
    safe = SafeReward(jerk_weight=0.0)
    far, near, end = (on_road(Road(d, 1, ROAD_RANGE, 0.0)) for d in (900.0, 300.0, 2.0))
    free = safe(far, far, DT)  # the drive term of these identical steps
    shaped = (safe(far, near, DT) - free) + (safe(near, end, DT) - free)
    assert shaped == pytest.approx(2.0 * (route_potential(end) - route_potential(far)))


def test_ending_at_the_lane_end_costs_its_penalty_never_more_than_a_crash() -> None:
    safe = SafeReward()
    standing = on_road(Road(3.0, 1, ROAD_RANGE, 0.0), speed=0.0)
    last = on_road(Road(3.0, 1, ROAD_RANGE, 0.0), speed=0.0, reason="lane_end")
    assert safe(standing, last, DT) == pytest.approx(-5.0)
    assert safe.lane_end_cost <= safe.collision_penalty
    with pytest.raises(ValueError, match="must not exceed collision_penalty"):
        SafeReward(lane_end_penalty=15.0, route_weight=3.0)


def test_on_an_open_road_the_route_terms_are_zero() -> None:
    safe = SafeReward()
    prev, obs = make_obs(speed=20.0), make_obs(speed=20.0)
    assert safe(prev, obs, DT) == safe(
        replace(prev, road=OPEN_ROAD), replace(obs, road=OPEN_ROAD), DT
    )


def test_the_safe_reward_makes_a_red_light_cost_more_than_driving_on_can_earn() -> None:
    reward = make_reward("safe")
    calm = make_obs(events=Events())
    passed = make_obs(time=1.1, events=Events(red_light=True))
    assert reward(calm, passed, 0.1) == -50.0
    assert reward(calm, passed, 0.1) < -1.0 / (1.0 - 0.98)  # worse than 50 steps of full pay
