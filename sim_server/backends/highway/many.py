"""The decisions of a multi-ego highway episode (protocol 1.4, ``egos`` > 1).

Every ego still driving has its command checked and its lane change begun (or refused) as the
one ego's is, then the decision's simulation steps run for all of them at once, each request
limited anew on each step (`_drive_many`). Each ego is judged alone: one that crashes, reaches
the end of the road or passes the end of its lane is observed at that step and taken off the
road, the others drive on; an ego whose drive ends is reported once (`Driven.over`).
"""

from __future__ import annotations

from protocol.messages import (
    AccelerationLimit,
    ActionSchema,
    AppliedAction,
    EgoObservation,
    EndReason,
    Events,
    MultiObservation,
)
from sim_server.backends.base import Commands, ego_part
from sim_server.backends.highway.egos import Driven, Episode, Turn
from sim_server.backends.highway.lane_changes import (
    lane_change_progress,
    refusal,
    start_lane_change,
)
from sim_server.backends.highway.observation import Observer
from sim_server.backends.highway.scene import DT
from sim_server.backends.highway.simulation import advance, collided_with, outcome
from sim_server.backends.rules import ended, limit_acceleration


def first_frame(episode: Episode, observer: Observer) -> MultiObservation:
    """Seq 0: every ego as handed over, standing still in the frame's action."""
    still = AppliedAction(0.0, 0, 0.0, 0)
    firsts = [observer.observe(episode, d.vehicle, None, 0, Events(), still) for d in episode.fleet]
    mine = tuple(ego_part(d.id, obs) for d, obs in zip(episode.fleet, firsts, strict=True))
    return MultiObservation(0, episode.time, mine)


def decide(
    episode: Episode, seq: int, commands: Commands, observer: Observer, schema: ActionSchema
) -> MultiObservation:
    """Apply every running ego's command; the frame of the decision."""
    turns = [_turn(episode, d, *commands[d.id]) for d in episode.fleet if not d.over]
    _drive_many(episode, seq, turns, observer, schema)
    ends: list[tuple[int, EndReason]] = []
    egos: list[EgoObservation] = []
    for turn in turns:
        action, events = turn.result()
        driven = turn.driven
        obs = turn.last or observer.observe(
            episode, driven.vehicle, driven.lane_change, seq, events, action
        )
        reason = EndReason.LANE_END if turn.lane_end else driven.end.check(obs)
        if reason is not None:
            obs = ended(obs, reason)
            driven.over = True
            ends.append((turn.steps, reason))  # in time, then in the egos' order
            if driven.vehicle in episode.road.vehicles:
                episode.road.vehicles.remove(driven.vehicle)
        egos.append(ego_part(driven.id, obs))
    ends.sort(key=lambda end: end[0])  # stable: within a step, the egos' order
    return _frame(episode, seq, tuple(egos), ends[-1][1] if ends else "")


def _turn(episode: Episode, driven: Driven, request: float, lane_change: int) -> Turn:
    """`driven`'s command checked and its lane change begun (or refused)."""
    refused = (
        refusal(episode, driven.vehicle, driven.lane_change, lane_change) if lane_change else ""
    )
    started = bool(lane_change) and not refused
    if started:
        driven.lane_change = start_lane_change(episode, driven.vehicle, lane_change)
    return Turn(driven, request, lane_change, refused, started)


def _drive_many(
    episode: Episode, seq: int, turns: list[Turn], observer: Observer, schema: ActionSchema
) -> None:
    """Run the decision's simulation steps for every ego at once, each request limited anew
    on each step; an ego that crashes or reaches the end of the road is observed at that step
    and taken off the road, the others drive on."""
    drives = episode.options.simulator_drives
    low, high = schema.acceleration_min, schema.acceleration_max
    for _ in range(episode.substeps):
        active = [t for t in turns if not t.stopped_inside]
        if not active:
            break
        for turn in active:
            ego = turn.driven.vehicle
            turn.why = AccelerationLimit.SIMULATOR
            if not drives:
                limit = float(ego.lane.speed_limit)
                ego.command, turn.why = limit_acceleration(
                    turn.request, float(ego.speed), limit, low, high, DT
                )
        advance(episode)
        for turn in active:
            ego = turn.driven.vehicle
            if not drives and ego.speed < 0.0:
                ego.speed = 0.0  # as for one ego
            turn.applied_total += float(ego.action["acceleration"])
            turn.limited_by = turn.limited_by or turn.why
            turn.steps += 1
            _judge_step(episode, turn)
        stopped = [t for t in active if t.stopped_inside]
        for turn in stopped:  # observed before any leaves: two egos that collide see each other
            action, events = turn.result()
            driven = turn.driven
            turn.last = observer.observe(
                episode, driven.vehicle, driven.lane_change, seq, events, action
            )
        for turn in stopped:
            episode.road.vehicles.remove(turn.driven.vehicle)


def _judge_step(episode: Episode, turn: Turn) -> None:
    """After a simulation step: `turn`'s crash, end of road, end of its lane or lane-change
    progress."""
    driven = turn.driven
    ego = driven.vehicle
    ending = outcome(episode, ego)
    if ending == EndReason.COLLISION:
        turn.collision_with = episode.ids.get(collided_with(episode, ego), "unknown")
    elif ending:
        turn.end_of_road = ending == EndReason.END_OF_ROAD
        turn.lane_end = ending == EndReason.LANE_END
    elif driven.lane_change is not None:
        completed, aborted = lane_change_progress(episode, ego, driven.lane_change)
        turn.completed, turn.aborted = turn.completed or completed, turn.aborted or aborted
        if completed or aborted:
            driven.lane_change = None


def _frame(
    episode: Episode, seq: int, egos: tuple[EgoObservation, ...], last_end: str
) -> MultiObservation:
    """The decision's frame: truncated at the time limit, terminated once no ego is left
    (with `last_end`, the reason of the last end)."""
    truncated = any(e.truncated for e in egos)
    terminated = not truncated and all(d.over for d in episode.fleet)
    reason = ""
    if truncated:
        reason = EndReason.TIME_LIMIT
    elif terminated:
        reason = last_end
    episode.done = truncated or terminated
    return MultiObservation(seq, episode.time, egos, terminated, truncated, reason)
