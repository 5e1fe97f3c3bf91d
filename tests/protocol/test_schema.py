from __future__ import annotations

import pytest

from protocol.messages import FieldSpec, Neighbour, Neighbours
from protocol.schema import NEIGHBOUR_SLOTS, OBSERVATION_FIELDS, Flattener
from tests.protocol.test_codec import make_observation


def test_every_field_has_unit_and_meaning_and_a_unique_name() -> None:
    names = [f.name for f in OBSERVATION_FIELDS]
    assert len(names) == len(set(names))
    assert all(f.unit and f.description for f in OBSERVATION_FIELDS)
    for slot in NEIGHBOUR_SLOTS:
        for part in ("present", "gap", "lateral", "speed"):
            assert f"{slot}_{part}" in names


def test_flat_vector_follows_the_schema_order() -> None:
    obs = make_observation()
    flat = Flattener()(obs)
    values = dict(zip([f.name for f in OBSERVATION_FIELDS], flat, strict=True))
    assert values["time"] == 31.2
    assert values["ego_speed"] == 15.0
    assert values["leader_present"] == 1.0
    assert values["leader_gap"] == 12.5
    assert values["leader_speed_diff"] == pytest.approx(1.0)
    assert values["left_leader_present"] == 0.0
    assert values["left_leader_gap"] == 200.0  # absent: the sensor range, with the flag at 0


def test_a_reordered_schema_reorders_the_vector() -> None:
    fields = (FieldSpec("leader_gap", "m", ""), FieldSpec("ego_speed", "m/s", ""))
    assert Flattener(fields)(make_observation()) == [12.5, 15.0]


def test_unknown_schema_fields_are_refused() -> None:
    with pytest.raises(ValueError, match="warp_factor"):
        Flattener((FieldSpec("warp_factor", "1", ""),))


def test_speed_diff_is_zero_without_leader() -> None:
    absent = Neighbour(False, 200.0, 0.0, 0.0)
    obs = make_observation(neighbours=Neighbours(*(absent,) * 6))
    flattener = Flattener()
    assert flattener(obs)[flattener.index("leader_speed_diff")] == 0.0
