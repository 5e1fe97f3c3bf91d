"""The action encodings and observation bounds of `RemoteEnv`, without a server."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium import spaces

from agent_client.envs.spaces import (
    ACTION_SPACES,
    MAX_SPEED,
    field_bounds,
    make_action_encoding,
    observation_space,
)
from protocol.messages import ROAD_RANGE, ActionSchema
from protocol.schema import OBSERVATION_FIELDS

SCHEMA = ActionSchema(acceleration_min=-6.0, acceleration_max=3.0)
CONCRETE = [name for name in ACTION_SPACES if name != "auto"]


def test_auto_is_a_flat_box_on_one_lane_and_the_hybrid_box_on_several() -> None:
    one = make_action_encoding("auto", SCHEMA, lanes=False)
    several = make_action_encoding("auto", SCHEMA, lanes=True)
    assert (one.name, one.space) == ("box", spaces.Box(-1.0, 1.0, (1,), np.float32))
    assert (several.name, several.space) == ("hybrid", spaces.Box(-1.0, 1.0, (2,), np.float32))


def test_flat_box_maps_minus_one_and_one_onto_the_servers_bounds() -> None:
    box = make_action_encoding("box", SCHEMA, lanes=True)
    assert box.decode(np.array([-1.0])) == (-6.0, 0)
    assert box.decode(np.array([1.0])) == (3.0, 0)
    assert box.decode(np.array([0.0])) == (-1.5, 0)
    assert box.decode(np.array([5.0])) == (3.0, 0)  # outside the box: clipped


@pytest.mark.parametrize(
    ("u", "lane"), [(-1.0, -1), (-0.34, -1), (-0.33, 0), (0.0, 0), (0.33, 0), (0.34, 1), (1.0, 1)]
)
def test_hybrid_second_component_selects_right_keep_left(u: float, lane: int) -> None:
    hybrid = make_action_encoding("hybrid", SCHEMA, lanes=True)
    assert hybrid.decode(np.array([1.0, u], np.float32))[1] == lane


def test_discrete_levels_cover_the_bounds_with_zero_and_every_lane() -> None:
    discrete = make_action_encoding("discrete", SCHEMA, lanes=True)
    assert discrete.space == spaces.Discrete(21)
    decoded = {discrete.decode(i) for i in range(21)}
    assert {a for a, _ in decoded} == {-6.0, -4.5, -3.0, -1.5, 0.0, 1.5, 3.0}
    assert {lane for _, lane in decoded} == {-1, 0, 1}
    assert len(decoded) == 21
    assert make_action_encoding("discrete", SCHEMA, lanes=False).space == spaces.Discrete(7)


def test_multi_discrete_has_a_lane_column_only_with_several_lanes() -> None:
    assert make_action_encoding("multi_discrete", SCHEMA, True).space == spaces.MultiDiscrete(
        [7, 3]
    )
    one = make_action_encoding("multi_discrete", SCHEMA, False)
    assert one.space == spaces.MultiDiscrete([7])
    assert one.decode(np.array([6])) == (3.0, 0)


@pytest.mark.parametrize("name", CONCRETE)
@pytest.mark.parametrize("lane_change", [-1, 0, 1])
def test_encode_then_decode_gives_the_decision_back(name: str, lane_change: int) -> None:
    encoding = make_action_encoding(name, SCHEMA, lanes=True)
    action = encoding.encode(1.5, lane_change)
    assert encoding.space.contains(action)
    acceleration, lane = encoding.decode(action)
    assert acceleration == pytest.approx(1.5, abs=1e-6)
    assert lane == (lane_change if encoding.lanes else 0)


@pytest.mark.parametrize("name", CONCRETE)
def test_every_sample_decodes_into_the_servers_bounds(name: str) -> None:
    encoding = make_action_encoding(name, SCHEMA, lanes=True)
    encoding.space.seed(0)
    for _ in range(200):
        acceleration, lane = encoding.decode(encoding.space.sample())
        assert -6.0 <= acceleration <= 3.0
        assert lane in (-1, 0, 1)


@pytest.mark.parametrize("name", CONCRETE)
def test_the_named_form_is_accepted_by_every_encoding(name: str) -> None:
    encoding = make_action_encoding(name, SCHEMA, lanes=True)
    assert encoding.decode({"acceleration": [0.7], "lane_change": -1}) == (
        pytest.approx(0.7),
        -1,
    )


def test_batches_decode_row_by_row() -> None:
    hybrid = make_action_encoding("hybrid", SCHEMA, lanes=True)
    accelerations, lanes = hybrid.decode_batch(np.array([[-1.0, 0.9], [1.0, -0.9]]), 2)
    assert accelerations.tolist() == [-6.0, 3.0]
    assert lanes.tolist() == [1, -1]


def test_unknown_names_and_too_few_levels_are_refused() -> None:
    with pytest.raises(ValueError, match="not one of"):
        make_action_encoding("continuous", SCHEMA, lanes=True)
    with pytest.raises(ValueError, match="at least 2"):
        make_action_encoding("discrete", SCHEMA, lanes=True, levels=1)


def test_every_observation_field_has_finite_bounds() -> None:
    box = observation_space(OBSERVATION_FIELDS, 200.0, SCHEMA)
    assert box.shape == (len(OBSERVATION_FIELDS),)
    assert np.isfinite(box.low).all()
    assert np.isfinite(box.high).all()
    assert (box.low < box.high).all()


def test_bounds_come_from_the_welcome_where_it_knows_them() -> None:
    by_name = {f.name: field_bounds(f, 150.0, SCHEMA) for f in OBSERVATION_FIELDS}
    assert by_name["leader_gap"] == (-150.0, 150.0)
    assert by_name["left_follower_lateral"] == (-150.0, 150.0)
    assert by_name["right_leader_present"] == (0.0, 1.0)
    assert by_name["ego_acceleration"] == (-6.0, 3.0)
    assert by_name["ego_speed"] == (0.0, MAX_SPEED)
    assert by_name["leader_speed_diff"] == (-MAX_SPEED, MAX_SPEED)
    assert by_name["ego_lane_count"][0] == 1.0
    assert by_name["lane_end"] == by_name["stop_line"] == (0.0, ROAD_RANGE)
