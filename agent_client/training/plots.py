"""Training curves as PNG (the paper's Figs. 3-8): reward, critic loss, mean Q and its bound."""

from __future__ import annotations

import math
from pathlib import Path

from agent_client.training.run_log import EPISODE_CSV, EVALUATION_CSV, read_rows


def _floats(rows: list[dict[str, str]], key: str) -> list[float]:
    values = []
    for row in rows:
        try:
            values.append(float(row[key]))
        except (KeyError, TypeError, ValueError):
            values.append(math.nan)
    return values


def plot_training(run: Path) -> Path:
    """Write ``training.png`` of a run folder; returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_rows(run / EPISODE_CSV)
    episodes = _floats(rows, "episode")
    fig, axes = plt.subplots(2, 2, figsize=(11, 7), constrained_layout=True)
    (reward, loss), (q, speed) = axes
    reward.plot(episodes, _floats(rows, "total_reward"), lw=0.8)
    reward.set(title="Total reward per episode", xlabel="episode", ylabel="reward")
    loss.plot(episodes, _floats(rows, "critic_loss"), lw=0.8, color="tab:red")
    loss.set(title="Mean critic loss per episode", xlabel="episode", ylabel="loss", yscale="log")
    q.plot(episodes, _floats(rows, "q_mean"), lw=0.8, color="tab:green", label="mean Q")
    bound = _floats(rows, "q_upper_bound")
    if bound and math.isfinite(bound[-1]):
        q.axhline(
            bound[-1], ls="--", color="k", label=f"upper bound r_max/(1-gamma) = {bound[-1]:.1f}"
        )
    q.set(title="Average Q value per episode (Appendix A)", xlabel="episode", ylabel="Q")
    q.legend(loc="lower right")
    speed.plot(
        episodes, _floats(rows, "average_speed"), lw=0.8, color="tab:purple", label="training"
    )
    evaluation_path = run / EVALUATION_CSV
    if evaluation_path.exists():
        evaluations = read_rows(evaluation_path)
        speed.plot(_floats(evaluations, "episode"), _floats(evaluations, "average_speed"), "o-",
                   color="tab:orange", label="greedy evaluation")  # fmt: skip
    speed.set(title="Average speed per episode", xlabel="episode", ylabel="m/s")
    speed.legend(loc="lower right")
    path = run / "training.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
