from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from agent_client.drivers.mobil import JERK_LIMIT, STANDSTILL_SPEED, IDMMobilDriver
from agent_client.drivers.policy import (
    RESIDUAL_RANGE,
    ActionScale,
    load_policy_driver,
    save_policy,
)
from agent_client.drivers.spec import training_settings
from agent_client.rl.checkpoint import load_checkpoint, save_checkpoint
from agent_client.rl.features import FeatureMap, FeatureMismatch
from agent_client.rl.lanes import LaneChoice
from agent_client.rl.td3 import Agent, TD3Config
from protocol.messages import (
    ROAD_RANGE,
    ActionSchema,
    Ego,
    Neighbour,
    Neighbours,
    Observation,
    Road,
)
from tests.protocol.test_codec import make_observation


def test_action_scale_maps_tanh_onto_asymmetric_bounds() -> None:
    scale = ActionScale.from_schema(ActionSchema(-6.0, 3.0))
    assert scale.to_env(-1.0) == -6.0
    assert scale.to_env(1.0) == 3.0
    assert scale.to_env(0.0) == -1.5
    for a in (-6.0, -2.0, 0.0, 2.5, 3.0):
        assert scale.to_env(scale.to_policy(a)) == pytest.approx(a)
    assert scale.to_policy(10.0) == 1.0


def free_road() -> Neighbours:
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    return Neighbours(absent, absent, absent, absent, absent, absent)


def test_a_residual_action_corrects_the_reference_within_a_comfortable_jerk() -> None:
    scale = ActionScale(-6.0, 3.0, residual="idm+mobil")
    obs = make_observation(ego=Ego(20.0, 0.2, 0, 1, 120.0, 25.0), neighbours=free_road())
    reference = IDMMobilDriver().acceleration(obs)
    assert scale.to_env(0.0, obs) == pytest.approx(reference)
    assert scale.to_env(1.0, obs) == pytest.approx(0.2 + JERK_LIMIT * 0.1)
    assert scale.to_env(-1.0, obs) == pytest.approx(0.2 - JERK_LIMIT * 0.1)
    one_second = ActionScale(-6.0, 3.0, residual="idm+mobil", interval=1.0)
    free = IDMMobilDriver().acceleration(obs, 1.0)  # 5 m/s³ over 1 s: IDM's own, unlimited
    assert one_second.to_env(-1.0, obs) == pytest.approx(free - RESIDUAL_RANGE)
    assert scale.to_policy(reference, obs) == pytest.approx(0.0)
    assert one_second.to_policy(free + RESIDUAL_RANGE / 2, obs) == pytest.approx(0.5)


def test_a_residual_correction_is_bounded_around_what_the_reference_wants() -> None:
    """An ego accelerating while its reference wants to brake: the correction reaches no
    further than RESIDUAL_RANGE above what the reference wants, however the jerk limit
    carries the acceleration it has (a policy cannot hold it there decision after decision)."""
    leader = Neighbour(True, 50.0, 0.0, 14.0, "veh.1")  # closing in: IDM brakes, not hard
    obs = make_observation(
        ego=Ego(20.0, 2.5, 0, 1, 120.0, 25.0), neighbours=replace(free_road(), leader=leader)
    )
    wanted = IDMMobilDriver().wanted_acceleration(obs)
    assert -3.0 < wanted < -RESIDUAL_RANGE / 2
    one_second = ActionScale(-6.0, 3.0, residual="idm+mobil", interval=1.0)
    assert one_second.to_env(1.0, obs) == pytest.approx(wanted + RESIDUAL_RANGE)
    scale = ActionScale(-6.0, 3.0, residual="idm+mobil")  # 0.1 s: the most it asks falls
    assert scale.to_env(1.0, obs) == pytest.approx(obs.ego.acceleration - JERK_LIMIT * 0.1)


def merging(lane_end: float, speed: float = 20.0) -> Observation:
    """An ego on an acceleration lane `lane_end` m before its end, beside a lane of traffic."""
    left = Neighbour(True, 30.0, 3.2, 20.0, "veh.2")
    return make_observation(
        ego=Ego(speed, 0.0, 0, 2, 120.0, 25.0),
        neighbours=replace(free_road(), left_leader=left),
        road=Road(lane_end, 1, ROAD_RANGE, 0.0),
    )


def test_a_residual_correction_fades_out_where_the_route_is_at_stake() -> None:
    scale = ActionScale(-6.0, 3.0, residual="idm+mobil", interval=1.0)
    reach = [scale.to_env(1.0, merging(d)) - scale.to_env(-1.0, merging(d)) for d in (400, 225)]
    assert reach == pytest.approx([2 * RESIDUAL_RANGE, RESIDUAL_RANGE])  # from 300 m to 150
    near = merging(120.0)
    reference = IDMMobilDriver().acceleration(near, 1.0)
    assert scale.to_env(1.0, near) == scale.to_env(-1.0, near) == pytest.approx(reference)
    assert scale.to_policy(reference, near) == scale.to_policy(2.0, near) == 0.0
    three_lanes = replace(near, road=Road(400.0, -3, ROAD_RANGE, 0.0))  # 150 m per lane
    assert scale.to_env(1.0, three_lanes) == scale.to_env(-1.0, three_lanes)


def test_a_residual_correction_fades_out_towards_a_standstill() -> None:
    """Moving off is the reference's: at rest a policy cannot hold the ego still (an ego that
    crawled at 0.5 m/s after a merge ended its episode as `stopped`)."""
    scale = ActionScale(-9.0, 9.0, residual="idm+mobil", interval=1.0)  # bounds out of reach

    def reach(speed: float) -> float:
        obs = make_observation(ego=Ego(speed, 0.0, 0, 1, 120.0, 25.0), neighbours=free_road())
        return scale.to_env(1.0, obs) - scale.to_env(-1.0, obs)

    assert reach(0.0) == 0.0
    assert reach(STANDSTILL_SPEED / 2) == pytest.approx(RESIDUAL_RANGE)
    assert reach(STANDSTILL_SPEED) == reach(20.0) == pytest.approx(2 * RESIDUAL_RANGE)
    standing = make_observation(ego=Ego(0.0, 0.0, 0, 1, 120.0, 25.0), neighbours=free_road())
    assert scale.to_env(-1.0, standing) == IDMMobilDriver().acceleration(standing, 1.0) > 1.0


def test_a_residual_action_brakes_hard_at_once_and_within_the_bounds() -> None:
    scale = ActionScale(-6.0, 3.0, residual="idm+mobil")
    leader = Neighbour(True, 4.0, 0.0, 5.0, "veh.1")  # close and much slower: IDM brakes hard
    obs = make_observation(
        ego=Ego(20.0, 0.0, 0, 1, 120.0, 25.0), neighbours=replace(free_road(), leader=leader)
    )
    assert scale.to_env(0.0, obs) == -6.0
    assert scale.to_env(-1.0, obs) == -6.0


def test_an_unknown_residual_base_is_refused() -> None:
    with pytest.raises(ValueError, match="idm\\+mobil"):
        ActionScale(-6.0, 3.0, residual="pid")


@pytest.mark.parametrize(("every", "gap_rule"), [(1, False), (10, True)])
def test_a_saved_policy_drives_like_the_agent(tmp_path: Path, every: int, gap_rule: bool) -> None:
    features, lanes = FeatureMap("lc", lane_phase_every=every), LaneChoice(3, every, gap_rule)
    agent = Agent(features.dim, 3, TD3Config(compile=False), seed=3)
    scale = ActionScale(-6.0, 3.0)
    save_policy(tmp_path / "policy.pt", agent.policy_state_dict(), features, scale, lanes)
    driver = load_policy_driver(tmp_path / "policy.pt")
    assert driver.lanes == lanes
    obs = make_observation()
    acceleration, lane_change = driver.act(obs)
    u, lane = agent.act(features(obs), explore=False, mask=lanes.mask(obs))
    assert acceleration == pytest.approx(scale.to_env(u))
    assert lane_change == (0, 1, -1)[lane]
    assert np.isfinite(acceleration)


def test_between_two_lane_decisions_a_saved_policy_keeps_its_lane(tmp_path: Path) -> None:
    features, lanes = FeatureMap("lc", lane_phase_every=10), LaneChoice(3, 10)
    agent = Agent(features.dim, 3, TD3Config(compile=False), seed=3)
    save_policy(tmp_path / "p.pt", agent.policy_state_dict(), features, ActionScale(-6, 3), lanes)
    driver = load_policy_driver(tmp_path / "p.pt")
    middle_lane = make_observation(ego=Ego(20.0, 0.0, 1, 3, 100.0, 22.2), seq=3)
    assert [driver.act(replace(middle_lane, seq=seq))[1] for seq in range(1, 10)] == [0] * 9


def test_a_residual_policy_steps_its_jerk_limit_over_the_interval_it_is_driven_at(
    tmp_path: Path,
) -> None:
    # Trained at 0.1 s, driven on a network whose SUMO step is 1 s: after a hard brake (a
    # junction's speed) it recovers at 5 m/s^3 over the second it has, not over 0.1 s.
    features, lanes = FeatureMap("road"), LaneChoice(1, 1)
    agent = Agent(features.dim, 1, TD3Config(compile=False), seed=3)
    scale = ActionScale(-6.0, 3.0, residual="idm+mobil", interval=0.1)
    save_policy(tmp_path / "p.pt", agent.policy_state_dict(), features, scale, lanes)
    driver = load_policy_driver(tmp_path / "p.pt")
    braked = Ego(8.0, -6.0, 0, 1, 120.0, 16.7)
    driven = [
        driver.act(make_observation(seq=seq, time=30.0 + seq, ego=braked, neighbours=free_road()))
        for seq in range(3)
    ]
    assert driven[0][0] <= -6.0 + JERK_LIMIT * 0.1 + 1e-9  # the trained interval, until seen
    assert driver.scale.interval == pytest.approx(1.0)
    assert driven[2][0] > -6.0 + JERK_LIMIT * 0.1 + 0.5  # a second's worth of recovery


def test_a_policy_of_an_older_feature_set_is_refused_with_the_reason(tmp_path: Path) -> None:
    features = FeatureMap("lc")
    agent = Agent(features.dim + 1, 3, TD3Config(compile=False), seed=3)  # "lc" lost a feature
    save_policy(
        tmp_path / "policy.pt", agent.policy_state_dict(), features, ActionScale(-6.0, 3.0),
        LaneChoice(3),
    )  # fmt: skip
    with pytest.raises(FeatureMismatch, match=r"takes 24 features.*'lc' now has 23"):
        load_policy_driver(tmp_path / "policy.pt")


def test_training_settings_come_from_the_run_folder(tmp_path: Path) -> None:
    (tmp_path / "config.json").write_text(
        json.dumps(
            {"scenario": "cflc", "decision_interval": 1.0, "scenario_options": {"flow": 900}}
        )
    )
    assert training_settings(str(tmp_path / "policy.pt")) == (
        "cflc",
        {"decision_interval": 1.0, "flow": 900},
    )
    assert training_settings("idm") == (None, {})
    assert training_settings(str(tmp_path / "elsewhere" / "policy.pt")) == (None, {})


def test_a_policy_saved_before_the_gap_rule_drives_without_it(tmp_path: Path) -> None:
    features, lanes = FeatureMap("lc"), LaneChoice(3)
    agent = Agent(features.dim, 3, TD3Config(compile=False), seed=3)
    save_policy(tmp_path / "p.pt", agent.policy_state_dict(), features, ActionScale(-6, 3), lanes)
    state = load_checkpoint(tmp_path / "p.pt")
    del state["lane_gap_rule"]  # as written by an older version
    save_checkpoint(tmp_path / "old.pt", state)
    assert not load_policy_driver(tmp_path / "old.pt").lanes.gap_rule
