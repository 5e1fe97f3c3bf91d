"""`MultiEgoCollector` and the trainer's ``egos`` path against a live ``sim-server --backend
fake``, whose many egos drive in one column behind its leader: every ego's steps reach the one
buffer, an ego that crashes stops contributing while the others drive on, the same seed gives
the same run; and the settings that cannot go together are refused."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import pytest

from agent_client.drivers.idm import IDMDriver
from agent_client.drivers.policy import ActionScale
from agent_client.errors import UsageError
from agent_client.rl.features import FeatureMap
from agent_client.rl.lanes import LaneChoice
from agent_client.training.config import TrainConfig, apply_overrides
from agent_client.training.run_log import read_rows
from agent_client.training.sampling.collect import Collected, Slot
from agent_client.training.sampling.many_egos import (
    EgoSlot,
    MultiEgoCollector,
    MultiEgoLink,
    batch_by_ego,
)
from agent_client.training.trainer import Trainer
from tests.agent_client.training import short_runs
from tests.conftest import RunningServer

EGOS = 4
IDS = [f"ego.{k}" for k in range(EGOS)]


class Scripted:
    """A chooser: IDM for every ego, full throttle for the egos named in `reckless`."""

    def __init__(self, scale: ActionScale, reckless: Sequence[str] = ()) -> None:
        self.scale = scale
        self.reckless = set(reckless)
        self.idm = IDMDriver()
        self.calls: list[list[str]] = []

    def __call__(self, slots: Sequence[Slot]) -> tuple[np.ndarray, np.ndarray]:
        ids = [slot.ego_id for slot in slots if isinstance(slot, EgoSlot)]
        self.calls.append(ids)
        us = [
            1.0 if ego_id in self.reckless else self.scale.to_policy(self.idm.act(slot.obs)[0])
            for ego_id, slot in zip(ids, slots, strict=True)
        ]
        return np.clip(np.array(us), -1.0, 1.0), np.zeros(len(slots), dtype=np.int64)


@pytest.fixture
def link(fake_server: RunningServer) -> Iterator[MultiEgoLink]:
    opened = MultiEgoLink.open(
        fake_server.address, "cf", egos=EGOS, timeout_s=5.0, max_episode_time=20.0
    )
    try:
        yield opened
    finally:
        opened.close()


def collector(link: MultiEgoLink, chooser: Scripted, starts: list[int]) -> MultiEgoCollector:
    seeds = iter(range(100, 10_000))
    return MultiEgoCollector(
        [link], FeatureMap("cf"), LaneChoice(1, 1), chooser.scale, chooser,
        lambda: next(seeds), starts.append,
    )  # fmt: skip


def one_simulation(collector: MultiEgoCollector, limit: int = 1000) -> list[Collected]:
    """Send and receive until the first simulation's last ego has ended."""
    received = []
    for _ in range(limit):
        collector.send()
        received.append(collector.receive())
        if received[-1].finished and not collector.running[0]:
            return received
    raise AssertionError(f"the simulation did not end within {limit} steps")


def test_every_egos_steps_become_transitions_and_each_drive_one_episode(
    link: MultiEgoLink,
) -> None:
    chooser = Scripted(ActionScale.from_schema(link.welcome.action))
    starts: list[int] = []
    received = one_simulation(collector(link, chooser, starts))
    assert starts == [0, 1, 2, 3]  # each ego's noise is reset when its drive starts
    transitions = [t for got in received for t in got.transitions]
    finished = [slot for got in received for slot in got.finished]
    assert sorted(slot.ego_id for slot in finished) == IDS
    assert [slot.env_index for slot in sorted(finished, key=lambda s: s.env_index)] == [0, 1, 2, 3]
    # one transition per ego and step: 200 decisions each to the time limit (20 s at 0.1 s)
    assert len(transitions) == sum(len(slot.states) for slot in finished) == EGOS * 200
    assert all(len(slot.episode.observations) == 201 for slot in finished)
    assert all(slot.episode.observations[-1].reason == "time_limit" for slot in finished)
    assert not any(t.terminated for t in transitions)  # the time limit bootstraps
    assert {slot.episode.seed for slot in finished} == {100}  # one simulation, one seed
    assert all(ids == IDS for ids in chooser.calls)  # one batch of every running ego
    # ... and into the one buffer, as the trainer stores them
    from agent_client.rl.replay import ReplayBuffer

    buffer = ReplayBuffer(10_000, FeatureMap("cf").dim, 0, 1)
    for t in transitions:
        buffer.add(t.x, t.u, t.lane, t.reward, t.next_x, t.terminated, t.mask, t.next_mask)
    assert len(buffer) == EGOS * 200


def test_an_ego_that_crashes_stops_contributing_while_the_others_drive_on(
    link: MultiEgoLink,
) -> None:
    chooser = Scripted(ActionScale.from_schema(link.welcome.action), reckless=["ego.0"])
    got = one_simulation(collector(link, chooser, []))
    ended = {slot.ego_id: (step, slot) for step, c in enumerate(got) for slot in c.finished}
    crash_step, crashed = ended["ego.0"]
    last = crashed.episode.observations[-1]
    assert last.terminated and last.reason == "collision"
    assert last.events.collision_with == "leader"
    assert set(ended) == set(IDS)
    assert all(step > crash_step for ego_id, (step, _) in ended.items() if ego_id != "ego.0")
    # its last transition is terminal (no bootstrap), the only one of the run
    terminal = [t for c in got for t in c.transitions if t.terminated]
    assert len(terminal) == 1
    assert np.array_equal(terminal[0].x, crashed.states[-1])
    # after the crash, every batch and every transition has the three others only
    assert all(ids == IDS[1:] for ids in chooser.calls[crash_step:])
    assert all(len(c.transitions) == EGOS - 1 for c in got[crash_step + 1 :])
    assert all(len(ended[ego_id][1].states) == 200 for ego_id in IDS[1:])


def test_each_ego_keeps_its_noise_row_whoever_has_ended() -> None:
    def slot(index: int) -> Slot:
        return EgoSlot(
            index,
            None,
            np.full(3, index, np.float32),
            np.array([True, index > 1, False]),
            None,
            ego_id=f"ego.{index}",
        )  # type: ignore[arg-type]

    x, masks, rows = batch_by_ego([slot(1), slot(3)])
    assert rows.tolist() == [1, 3]
    assert x[:, 0].tolist() == [0.0, 1.0, 0.0, 3.0]
    assert masks.tolist() == [[True, False, False]] * 3 + [[True, True, False]]


FAST = {
    "eval_every": 0,
    "checkpoint_every": 5,
    "scenario_options": {"max_episode_time": 3.0},
    "learner": {"learning_starts": 150, "batch_size": 32, "compile": False},
}


def train(address: str, out: Path, **changes: object) -> Trainer:
    return short_runs.train(address, out, FAST, **changes)


def test_the_trainer_learns_from_every_ego_with_one_shared_policy(
    fake_server: RunningServer, tmp_path: Path
) -> None:
    trainer = train(fake_server.address, tmp_path / "run", egos=EGOS, episodes=12, seed=3)
    rows = read_rows(tmp_path / "run" / "episodes.csv")
    assert [int(r["episode"]) for r in rows] == list(range(1, 13))
    assert sorted({r["ego"] for r in rows}) == IDS  # one row per ego-episode
    assert len({r["seed"] for r in rows}) == 3  # three simulations of four egos
    assert trainer.progress.global_step == len(trainer.buffer) == sum(int(r["steps"]) for r in rows)
    assert trainer.progress.updates > 0  # learning started, the policy acted for all at once
    assert len(trainer.agent.noises) == EGOS


def test_the_same_seed_gives_the_same_run(fake_server: RunningServer, tmp_path: Path) -> None:
    runs = []
    for name in ("a", "b"):
        trainer = train(fake_server.address, tmp_path / name, egos=3, episodes=9, seed=5)
        rows = read_rows(tmp_path / name / "episodes.csv")
        runs.append(([{k: v for k, v in r.items() if k != "wall_time"} for r in rows], trainer))
    (rows_a, a), (rows_b, b) = runs
    assert rows_a == rows_b
    assert a.progress.updates == b.progress.updates > 0
    size = len(a.buffer)
    assert size == len(b.buffer)
    for name in ("obs", "acceleration", "reward", "next_obs", "terminated"):
        assert np.array_equal(getattr(a.buffer, name)[:size], getattr(b.buffer, name)[:size])
    for mine, theirs in zip(
        a.agent.policy_state_dict()["actor"], b.agent.policy_state_dict()["actor"], strict=True
    ):
        assert mine.equal(theirs)


def test_evaluations_stay_one_ego_in_the_same_session(
    fake_server: RunningServer, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    train(
        fake_server.address, out, egos=3, episodes=9, seed=1,
        eval_every=3, eval_episodes=2, eval_gate=0,
    )  # fmt: skip
    evaluations = read_rows(out / "evaluations.csv")
    assert len(evaluations) >= 1
    assert len(read_rows(out / "episodes.csv")) == 9


def test_many_egos_with_ray_sampling_are_refused() -> None:
    with pytest.raises(UsageError, match="egos 4 needs sampling = local"):
        apply_overrides(TrainConfig(), {"egos": 4, "sampling": "ray"})
    with pytest.raises(UsageError, match="egos must be a whole number of at least 1, got 0"):
        apply_overrides(TrainConfig(), {"egos": 0})
    assert apply_overrides(TrainConfig(), {"egos": 1, "sampling": "ray"}).egos == 1


def test_the_cli_refuses_egos_with_ray_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from agent_client.cli.main import main

    status = main(["train", "--egos", "4", "--sampling", "ray", "--server", "tcp://127.0.0.1:9"])
    error = capsys.readouterr().err
    assert status == 2
    assert error.count("\n") == 1 and "egos 4 needs sampling = local" in error
