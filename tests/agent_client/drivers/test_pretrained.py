"""The shipped policies: each loads as a driver by name, with its model card and settings."""

from __future__ import annotations

import pytest

from agent_client.drivers import pretrained
from agent_client.drivers.policy import PolicyDriver
from agent_client.drivers.spec import load_driver
from agent_client.errors import UsageError

SHIPPED = ("cf", "cflc", "roads")
"""The policies the documented commands trained (docs/learner.md, README "Drivers")."""


def test_the_documented_policies_are_shipped() -> None:
    assert set(SHIPPED) <= set(pretrained.names())


@pytest.mark.parametrize("name", SHIPPED)
def test_a_shipped_policy_loads_by_name_with_its_card_and_settings(name: str) -> None:
    driver = load_driver(f"{pretrained.PREFIX}{name}")
    assert isinstance(driver, PolicyDriver)
    card = (pretrained.FOLDER / f"{name}.md").read_text()
    for part in ("agent-client train", "seed", "| map |"):  # the command, its seeds, its table
        assert part in card, f"{name}.md has no {part!r}"
    settings = pretrained.settings(name)
    assert settings["scenario"] and settings["decision_interval"] > 0


def test_an_unknown_name_is_a_usage_error_naming_the_shipped_ones() -> None:
    with pytest.raises(UsageError, match="cflc"):
        load_driver("pretrained:nosuch")
    assert pretrained.policy_file("nosuch") is None and pretrained.settings("nosuch") == {}
