"""Which lane choices can happen: none that does not exist, none during a change, and only at a
lane decision."""

from __future__ import annotations

import numpy as np
import pytest

from agent_client.rl.lanes import LANE_COMMANDS, LaneChoice, choose_lanes
from protocol.messages import Ego
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
