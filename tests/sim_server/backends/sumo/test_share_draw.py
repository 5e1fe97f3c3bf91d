"""`ShareDraw`: which vehicles become egos at a share of the traffic (pure logic, no SUMO)."""

from __future__ import annotations

import pytest

from sim_server.backends.sumo.egos import ShareDraw


@pytest.mark.parametrize(("share", "on_road", "count"), [(0.25, 68, 17), (0.1, 15, 2), (1.0, 9, 9)])
def test_the_hand_over_takes_the_rounded_share_in_the_roads_order(
    share: float, on_road: int, count: int
) -> None:
    vehicles = [f"human0.{k}" for k in range(on_road)]
    chosen = ShareDraw(share, seed=4).at_hand_over(vehicles)
    assert len(chosen) == count
    assert chosen == [v for v in vehicles if v in chosen]  # in the order given
    assert ShareDraw(share, seed=4).at_hand_over(vehicles) == chosen  # seeded
    assert ShareDraw(share, seed=5).at_hand_over(vehicles) != chosen or count == on_road


def test_the_hand_over_takes_at_least_one() -> None:
    assert len(ShareDraw(0.01, seed=1).at_hand_over(["a", "b", "c"])) == 1


@pytest.mark.parametrize("share", [0.1, 0.25, 0.5, 1.0])
def test_arrivals_join_at_exactly_the_share_spread_evenly(share: float) -> None:
    draw = ShareDraw(share, seed=2)
    joined: list[str] = []
    for batch in range(100):  # arrivals in batches of 0 to 3, as decisions bring them
        draw.entered += [f"v{batch}.{k}" for k in range(batch % 4)]
        joined += draw.joining()
        assert not draw.entered  # each arrival is judged once
        assert abs(len(joined) - share * sum(b % 4 for b in range(batch + 1))) <= 1.0
    batches = [int(v.split(".")[0][1:]) for v in joined]
    assert min(batches) < 15 and max(batches) > 85  # spread over the whole run


def test_the_first_arrival_to_join_depends_on_the_seed() -> None:
    firsts = set()
    for seed in range(20):
        draw = ShareDraw(0.1, seed=seed)
        draw.entered += [f"v{k}" for k in range(10)]
        firsts.add(draw.joining()[0])
    assert len(firsts) > 3
