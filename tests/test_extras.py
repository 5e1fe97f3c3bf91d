"""The optional learners stay optional: `server` and `client` do not grow, `all` (what the test
command installs, so that the Ray, RLlib and Stable-Baselines3 tests run) has them."""

from __future__ import annotations

import tomllib
from pathlib import Path

EXTRAS = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())[
    "project"
]["optional-dependencies"]
LEARNERS = ("ray", "stable-baselines3", "torch")


def names(extra: str) -> set[str]:
    return {req.split("[")[0].split("=")[0].split(">")[0].split("<")[0] for req in EXTRAS[extra]}


def test_server_and_client_installs_bring_no_third_party_learner() -> None:
    assert not names("server") & set(LEARNERS)
    assert not names("client") & {"ray", "stable-baselines3"}


def test_the_test_suites_install_has_every_learner_extra() -> None:
    (everything,) = [req for req in EXTRAS["all"] if req.startswith("av-bridge[")]
    included = set(everything.removeprefix("av-bridge[").removesuffix("]").split(","))
    assert {"server", "client", "sb3", "ray", "rllib"} <= included
    assert EXTRAS["rllib"] == ["ray[rllib]==2.60.0"]
    assert EXTRAS["sb3"] == ["stable-baselines3==2.9.2"]
