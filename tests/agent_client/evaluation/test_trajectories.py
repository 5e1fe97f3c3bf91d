"""Episode traces from hand-built observations, the pictures drawn from them, and the report's
choice of episodes to draw (default, chosen, refused)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

from agent_client.cli import main
from agent_client.constants import PAPER_SPEED_LIMIT
from agent_client.drivers.episode import Episode
from agent_client.errors import UsageError
from agent_client.evaluation.evaluate import EpisodeRecord, Evaluation
from agent_client.evaluation.report import (
    check_trajectory_seeds,
    combine_reports,
    most_critical,
    trajectory_plan,
    write_report,
)
from agent_client.evaluation.trajectories import VEHICLE_LENGTH, EpisodeTrace, neighbour_front
from agent_client.evaluation.trajectory_plots import plot_time_series, plot_time_space
from protocol.messages import AppliedAction, Ego, Events, Neighbour, Neighbours
from tests.agent_client.evaluation.test_evaluate import synthetic_evaluation
from tests.protocol.test_codec import make_observation

ABSENT = Neighbour(False, 200.0, 0.0, 0.0)
PNG = b"\x89PNG\r\n\x1a\n"
NO_ACTION = AppliedAction(0, 0, 0, 0)


def neighbours(**present: Neighbour) -> Neighbours:
    slots = ("left_leader", "left_follower", "leader", "follower", "right_leader",
             "right_follower")  # fmt: skip
    return Neighbours(**{slot: present.get(slot, ABSENT) for slot in slots})


def lane_change_observations() -> list:
    """The ego in lane 1 of 3 at 10 m/s changes left (started at 30.1 s, completed at 30.2 s);
    vehicle "A" is its leader, then (the ego in lane 2) its right leader: the same lane 1."""
    ego = Ego(10.0, 0.0, 1, 3, 100.0, PAPER_SPEED_LIMIT)
    return [
        make_observation(
            seq=0, time=30.0, ego=ego, events=Events(), action=NO_ACTION,
            neighbours=neighbours(leader=Neighbour(True, 20.0, 0.0, 9.0, "A"),
                                  follower=Neighbour(True, 10.0, 0.0, 11.0, "B"),
                                  left_leader=Neighbour(True, 30.0, 3.2, 12.0, "C"),
                                  right_follower=Neighbour(True, 15.0, -3.2, 8.0, "D")),
        ),
        make_observation(
            seq=1, time=30.1, ego=Ego(10.0, 1.0, 1, 3, 101.0, PAPER_SPEED_LIMIT, 1),
            events=Events(lane_change_started=True), action=AppliedAction(1.0, 1, 1.0, 1),
            neighbours=neighbours(leader=Neighbour(True, 19.9, 0.0, 9.0, "A"),
                                  left_leader=Neighbour(False, 0.0, 0.0, 0.0, "ghost")),
        ),
        make_observation(
            seq=2, time=30.2, ego=Ego(10.1, 0.5, 2, 3, 102.0, PAPER_SPEED_LIMIT),
            events=Events(lane_change_completed=True), action=AppliedAction(0.5, 0, 0.5, 0),
            neighbours=neighbours(right_leader=Neighbour(True, 19.0, -3.2, 9.0, "A"),
                                  left_follower=Neighbour(True, 5.0, 3.2, 10.0, "")),
        ),
    ]  # fmt: skip


def test_neighbour_fronts_from_gaps() -> None:
    # A leader's rear is at the ego's front + gap; its front one vehicle length further.
    assert neighbour_front(100.0, 20.0, ahead=True) == pytest.approx(125.0)
    # A follower's front is at the ego's rear (front - length) minus the gap.
    assert neighbour_front(100.0, 10.0, ahead=False) == pytest.approx(85.0)
    assert VEHICLE_LENGTH == 5.0


def test_trace_of_the_ego_and_its_neighbours() -> None:
    trace = EpisodeTrace.from_observations(lane_change_observations(), 0.1, seed=7)
    assert trace.seed == 7 and trace.start == 30.0 and trace.lane_count == 3
    assert trace.position.tolist() == [100.0, 101.0, 102.0]
    assert trace.lane.tolist() == [1, 1, 2]
    assert trace.gap[:2].tolist() == pytest.approx([20.0, 19.9]) and np.isnan(trace.gap[2])
    # Jerk at the simulator's step: (1.0 - 0.0) / 0.1 and (0.5 - 1.0) / 0.1.
    assert np.isnan(trace.jerk[0]) and trace.jerk[1:] == pytest.approx([10.0, -5.0])
    assert trace.lane_change_starts.tolist() == [30.1]
    assert trace.lane_change_directions.tolist() == [1]
    assert trace.lane_change_completions.tolist() == [30.2]
    assert len(trace.collisions) == 0 and len(trace.lane_change_aborts) == 0
    # Absent slots (whatever their id) and vehicles without an id are not tracked.
    assert set(trace.neighbours) == {"A", "B", "C", "D"}
    leader = trace.neighbours["A"]
    assert leader.step.tolist() == [0, 1, 2]
    assert leader.position == pytest.approx([125.0, 101.0 + 19.9 + 5.0, 102.0 + 19.0 + 5.0])
    assert leader.lane.tolist() == [1, 1, 1]  # leader in lane 1, then right of the ego in lane 2
    assert leader.speed.tolist() == [9.0, 9.0, 9.0]
    assert trace.neighbours["B"].position == pytest.approx([85.0])
    assert trace.neighbours["C"].lane.tolist() == [2]
    assert trace.neighbours["C"].position == pytest.approx([135.0])
    assert trace.neighbours["D"].lane.tolist() == [0]
    assert trace.neighbours["D"].position == pytest.approx([80.0])


def test_a_trace_needs_observations() -> None:
    with pytest.raises(ValueError, match="no observations"):
        EpisodeTrace.from_observations([], 0.1)


def test_the_record_of_an_episode_keeps_its_trace() -> None:
    recorder = Episode(episode=0, seed=5, step_length=0.1)
    for observation in lane_change_observations():
        recorder.add(observation, 0.0)
    trace = EpisodeRecord.from_episode(recorder).trace
    assert trace is not None and trace.seed == 5 and set(trace.neighbours) == {"A", "B", "C", "D"}


def long_observations(lanes: int, collide: bool) -> list:
    """A 30 s episode: the ego at 10 m/s behind "A", changing left at 10 s when there are
    lanes (completed at 12 s, in the new lane from 11 s), a neighbour in every other lane,
    and a collision with "A" at the end if asked."""
    observations = []
    lane = 0
    for step in range(301):
        t = 0.1 * step
        lane = 1 if lanes > 1 and t >= 11.0 else 0
        position = 10.0 * t
        others = {"leader": Neighbour(True, 20.0 - 0.5 * t, 0.0, 9.5, "A" if lane == 0 else "E")}
        if lanes > 1:
            side = "right_follower" if lane else "left_follower"
            others[side] = Neighbour(True, 15.0 + 0.2 * t, 3.2, 12.0 - 0.3 * t, "F")
        last = step == 300
        events = Events(
            lane_change_started=lanes > 1 and step == 100,
            lane_change_completed=lanes > 1 and step == 120,
            collision=collide and last,
            collision_with="A" if collide and last else "",
        )
        action = AppliedAction(0.0, 1, 0.0, 1) if events.lane_change_started else NO_ACTION
        observations.append(
            make_observation(
                seq=step, time=30.0 + t, events=events, action=action, neighbours=neighbours(**others),
                ego=Ego(10.0, 0.3 * np.sin(t), lane, lanes, position, PAPER_SPEED_LIMIT),
                terminated=last, reason="collision" if collide and last else "",
                ceiling=None,
            )
        )  # fmt: skip
    return observations


@pytest.mark.parametrize(("lanes", "collide"), [(1, False), (3, True)])
def test_the_pictures_are_real_pngs(tmp_path: Path, lanes: int, collide: bool) -> None:
    trace = EpisodeTrace.from_observations(long_observations(lanes, collide), 0.1, seed=3)
    space, series = tmp_path / "space.png", tmp_path / "series.png"
    plot_time_space(trace, space, "a time-space diagram")
    other = EpisodeTrace.from_observations(long_observations(lanes, False), 0.1, seed=3)
    plot_time_series({"policy": trace, "baseline": other}, {"policy": "p"}, series, "series")
    for path in (space, series):
        data = path.read_bytes()
        assert data[:8] == PNG
        assert len(data) > 20_000  # axes, lines and labels, not an empty canvas


def traced_evaluation() -> Evaluation:
    """The synthetic 3-lane evaluation (seeds 0-3) with traces; the policy's episode on seed 2
    has the smallest minimum TTC."""
    evaluation = synthetic_evaluation(lanes=3)
    for run in evaluation.drivers().values():
        for record in run.records:
            seed = record.summary.seed
            record.trace = EpisodeTrace.from_observations(long_observations(3, False), 0.1, seed)
    evaluation.policy.records[2].summary.min_ttc = 1.25
    return evaluation


def test_the_default_episodes_are_the_first_seed_and_the_most_critical() -> None:
    evaluation = traced_evaluation()
    plan = trajectory_plan(evaluation)
    assert [entry["seed"] for entry in plan] == [0, 2]
    assert plan[0]["why"] == "the first seed"
    assert "smallest minimum TTC, 1.25 s" in plan[1]["why"]
    assert plan[1]["time_space"] == {
        "policy": "time_space_2_policy.png",
        "baseline": "time_space_2_baseline.png",
        "cf_policy": "time_space_2_cf_policy.png",
    }
    assert plan[1]["time_series"] == "time_series_2.png"
    # The first seed is the most critical: one entry with both reasons.
    evaluation.policy.records[0].summary.collisions = 1
    plan = trajectory_plan(evaluation)
    assert [entry["seed"] for entry in plan] == [0]
    assert plan[0]["why"] == "the first seed; the policy's most critical episode (a collision)"


def test_the_most_critical_episode() -> None:
    records = synthetic_evaluation(lanes=1).policy.records
    for record in records:
        record.summary.min_ttc = None
    records[3].summary.min_time_headway = 0.4
    assert most_critical(records) == (
        3, "the policy's most critical episode (smallest minimum time headway, 0.40 s)"
    )  # fmt: skip
    for record in records:
        record.summary.min_time_headway = None
    assert most_critical(records) is None
    assert most_critical([]) is None


def test_chosen_seeds_and_refused_ones() -> None:
    evaluation = traced_evaluation()
    plan = trajectory_plan(evaluation, [3, 1])
    assert [entry["seed"] for entry in plan] == [3, 1]
    assert all(entry["why"] == "chosen (--trajectory-seeds)" for entry in plan)
    with pytest.raises(
        UsageError, match=r"--trajectory-seeds 7 9: not among the evaluated seeds \(0\.\.3\)"
    ):
        trajectory_plan(evaluation, [1, 7, 9])
    with pytest.raises(UsageError, match=r"\(5\)"):
        check_trajectory_seeds([6], [5])


def test_records_without_traces_draw_nothing() -> None:
    assert trajectory_plan(synthetic_evaluation(lanes=3)) == []


def test_the_report_draws_lists_and_links_the_pictures(tmp_path: Path) -> None:
    out = tmp_path / "eval" / "cflc"
    text = write_report(out, traced_evaluation()).read_text()
    metrics = json.loads((out / "metrics.json").read_text())
    plan = metrics["figures"]["trajectories"]
    files = [
        name for entry in plan for name in [entry["time_series"], *entry["time_space"].values()]
    ]
    assert len(files) == 8  # 2 seeds x (time series + 3 drivers)
    assert "## Trajectories of chosen episodes" in text
    assert "### Seed 2: the policy's most critical episode" in text
    for name in files:
        assert (out / name).read_bytes()[:8] == PNG
        assert f"]({name})" in text
    combined = combine_reports(tmp_path / "main", [out], "Main").read_text()
    for name in files:
        assert f"](../eval/cflc/{name})" in combined
        assert (tmp_path / "main" / "../eval/cflc" / name).is_file()


def test_a_report_without_traces_says_so(tmp_path: Path) -> None:
    text = write_report(tmp_path, synthetic_evaluation(lanes=1)).read_text()
    assert "No episode traces in these records" in text
    assert json.loads((tmp_path / "metrics.json").read_text())["figures"]["trajectories"] == []


def test_bad_trajectory_seeds_are_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    started = time.monotonic()
    argv = ["evaluate", "--policy", "idm", "--server", "tcp://127.0.0.1:9", "--timeout", "30",
            "--episodes", "3", "--seed", "10", "--trajectory-seeds", "11", "99"]  # fmt: skip
    assert main(argv) == 2
    assert time.monotonic() - started < 10.0  # refused before connecting
    err = capsys.readouterr().err.strip()
    assert err == "agent-client: --trajectory-seeds 99: not among the evaluated seeds (10..12)"
