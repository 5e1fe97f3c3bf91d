"""Which lane choices can happen: none that does not exist, none during a change, and only at a
lane decision."""

from __future__ import annotations

import numpy as np
import pytest

from agent_client.rl.lanes import (
    LANE_COMMANDS,
    SAFE_STANDSTILL_M,
    LaneChoice,
    choose_lanes,
    secure_gap,
)
from protocol.messages import ROAD_RANGE, Ego, Neighbour, Neighbours, Road
from tests.protocol.test_codec import make_observation


def ego(lane: int, lanes: int = 3, changing: int = 0) -> Ego:
    return Ego(20.0, 0.0, lane, lanes, 100.0, 22.2, changing_lane=changing)


@pytest.mark.parametrize(
    ("lane", "changing", "expected"),
    [
        (1, 0, [True, True, True]),
        (0, 0, [True, True, False]),  # no lane to the right of the rightmost
        (2, 0, [True, False, True]),  # none to the left of the leftmost
        (1, 1, [True, False, False]),  # a change under way: keep only
        (1, -1, [True, False, False]),
    ],
)
def test_masks_follow_the_road_and_the_change_under_way(
    lane: int, changing: int, expected: list[bool]
) -> None:
    assert LaneChoice(3).mask(make_observation(ego=ego(lane, changing=changing))).tolist() == (
        expected
    )


def test_between_lane_decisions_only_keep_is_possible() -> None:
    lanes = LaneChoice(3, every=10)
    middle = ego(1)
    due = [lanes.mask(make_observation(ego=middle, seq=seq)).tolist() for seq in range(21)]
    assert [seq for seq, mask in enumerate(due) if mask[1]] == [0, 10, 20]
    assert all(mask[0] for mask in due)
    assert lanes.phase(make_observation(seq=25)) == pytest.approx(0.5)


def test_one_lane_choice_is_keep_only_and_commands_are_keep_left_right() -> None:
    assert LaneChoice(1).mask(make_observation()).tolist() == [True]
    assert LANE_COMMANDS == (0, 1, -1)
    with pytest.raises(ValueError, match="n_choices"):
        LaneChoice(2)
    with pytest.raises(ValueError, match="every"):
        LaneChoice(3, every=0)


def test_choose_lanes_takes_the_best_valid_choice_and_explores_only_valid_ones() -> None:
    q = np.array([[1.0, 5.0, 3.0], [2.0, 1.0, 9.0]])
    valid = np.array([[True, False, True], [True, True, False]])
    assert choose_lanes(q, valid, 0.0, None).tolist() == [2, 0]
    rng = np.random.default_rng(0)
    explored = np.array([choose_lanes(q, valid, 1.0, rng) for _ in range(200)])
    assert set(explored[:, 0]) == {0, 2} and set(explored[:, 1]) == {0, 1}


def near(gap: float, speed: float) -> Neighbour:
    return Neighbour(True, gap, 3.2, speed, "v")


ABSENT = Neighbour(False, 200.0, 0.0, 0.0)


def sides(**slots: Neighbour) -> Neighbours:
    names = ("left_leader", "left_follower", "leader", "follower", "right_leader", "right_follower")
    return Neighbours(**{name: slots.get(name, ABSENT) for name in names})


def test_the_secure_gap_is_standstill_reaction_and_braking_difference() -> None:
    assert secure_gap(0.0, 0.0) == SAFE_STANDSTILL_M
    assert secure_gap(20.0, 20.0) == pytest.approx(2.5 + 20.0)  # same speed: no braking term
    assert secure_gap(20.0, 10.0) == pytest.approx(2.5 + 20.0 + (400 - 100) / 9.0)
    assert secure_gap(10.0, 20.0) == pytest.approx(2.5 + 10.0)  # a faster leader: none


@pytest.mark.parametrize(
    ("slots", "expected"),
    [
        ({}, [True, True, True]),  # empty lanes either side
        ({"left_leader": near(10.0, 20.0)}, [True, False, True]),  # 10 m < 22.5 m ahead
        ({"left_leader": near(60.0, 15.0)}, [True, True, True]),
        ({"right_follower": near(15.0, 25.0)}, [True, True, False]),  # a fast car behind
        ({"right_follower": near(80.0, 25.0)}, [True, True, True]),
        ({"left_follower": near(5.0, 5.0), "right_leader": near(5.0, 30.0)}, [True, False, False]),
    ],
)
def test_the_gap_rule_masks_changes_into_gaps_visibly_too_small(
    slots: dict[str, Neighbour], expected: list[bool]
) -> None:
    obs = make_observation(ego=ego(1), neighbours=sides(**slots))  # the ego at 20 m/s
    assert LaneChoice(3, gap_rule=True).mask(obs).tolist() == expected
    assert LaneChoice(3).mask(obs).tolist() == [True, True, True]  # without it: the road only


@pytest.mark.parametrize(
    ("lane_end", "expected"),
    [(230.0, [False, True, False]), (250.0, [True, False, False])],
)
def test_near_the_lane_end_the_change_towards_the_route_is_the_choice(
    lane_end: float, expected: list[bool]
) -> None:
    """Within 12 s of the end (240 m at 20 m/s) the route's change is asked for at every
    decision, whatever the gap (the simulator refuses an unsafe one); farther it is masked as
    any other."""
    merging = Road(lane_end, 1, ROAD_RANGE, 0.0)
    blocked = sides(left_leader=near(10.0, 20.0), right_leader=near(10.0, 20.0))
    obs = make_observation(seq=3, ego=ego(1), neighbours=blocked, road=merging)
    assert LaneChoice(3, every=10, gap_rule=True).mask(obs).tolist() == expected


@pytest.mark.parametrize(
    ("exit_in", "expected"),
    [(400.0, [True, False, True]), (1000.0, [True, True, True])],
)
def test_a_change_away_from_the_route_is_masked_where_it_leaves_too_little_to_come_back(
    exit_in: float, expected: list[bool]
) -> None:
    """In the middle lane, the exit to the right 400 m ahead (its lane, the right one, leads
    on): left would leave 2 lanes to cross in 400 m, less than 24 s per lane at 20 m/s; with
    the exit beyond the road ahead's range both ways are open."""
    exiting = Road(exit_in, -1, exit_in, ROAD_RANGE)
    obs = make_observation(seq=0, ego=ego(1), neighbours=sides(), road=exiting)
    assert LaneChoice(3, every=10).mask(obs).tolist() == expected


def test_in_the_route_lane_a_change_into_a_lane_that_ends_is_masked() -> None:
    """On the main road beside an acceleration lane that ends in 300 m: right is masked."""
    beside_a_ramp = Road(ROAD_RANGE, 0, ROAD_RANGE, 300.0)
    obs = make_observation(seq=0, ego=ego(1), neighbours=sides(), road=beside_a_ramp)
    assert LaneChoice(3, every=10).mask(obs).tolist() == [True, True, False]


def test_without_the_routes_masks_the_policy_decides_its_mandatory_changes() -> None:
    """Near the end of the lane it must leave, the integrated driver's choices stay its own
    (the safety layer asks for the change only where the lane end is about to be missed)."""
    road = Road(lane_end=60.0, lanes_to_change=1, left_lane_end=ROAD_RANGE, right_lane_end=0.0)
    obs = make_observation(ego=ego(0), road=road)
    assert LaneChoice(3).mask(obs).tolist() == [False, True, False]  # the route's, or nothing
    assert LaneChoice(3, route_masks=False).mask(obs).tolist() == [True, True, False]


@pytest.mark.parametrize(("lane_end", "offered"), [(230.0, True), (250.0, False)])
def test_without_the_routes_masks_the_routes_change_is_offered_at_every_decision(
    lane_end: float, offered: bool
) -> None:
    """Between two lane decisions, within 12 s of the end of the lane the route must leave
    (240 m at 20 m/s), the change towards the route may be asked, whatever the visible gap
    (as IDM + MOBIL asks it at every decision); keep stays possible, the other side not;
    farther, only keep."""
    merging = Road(lane_end, 1, ROAD_RANGE, 0.0)
    blocked = sides(left_leader=near(10.0, 20.0), right_leader=near(10.0, 20.0))
    obs = make_observation(seq=3, ego=ego(1), neighbours=blocked, road=merging)
    lanes = LaneChoice(3, every=10, gap_rule=True, route_masks=False)
    assert lanes.mask(obs).tolist() == [True, offered, False]


def test_with_the_reference_as_its_default_the_policy_may_follow_it_or_choose_its_own() -> None:
    """Four choices: the reference's change first, then keep / left / right of the policy's
    own, so that a policy cloned on the reference starts as the reference and leaves it only
    where a choice of its own is worth more."""
    wants_left = LaneChoice(4, reference=lambda obs, due: 1)
    obs = make_observation(ego=ego(1))
    assert wants_left.mask(obs).tolist() == [True, True, True, True]
    assert [wants_left.command(i, obs) for i in range(4)] == [1, 0, 1, -1]
    assert wants_left.index_of(1, obs) == 0 and wants_left.index_of(-1, obs) == 3
    assert wants_left.index_of(0, obs) == 1
    leftmost = make_observation(ego=ego(2))
    assert wants_left.command(0, leftmost) == 0  # no lane there: the reference keeps
    assert wants_left.mask(leftmost).tolist() == [True, True, False, True]
    with pytest.raises(ValueError, match="reference"):
        LaneChoice(4)
