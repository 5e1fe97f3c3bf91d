"""Every name the README and docs/ show is importable where they say it is."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

import agent_client

ROOT = Path(__file__).resolve().parents[2]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FROM_IMPORT = re.compile(r"from ((?:agent_client|protocol|sim_server)[\w.]*) import ([\w, ]+)")
DOTTED = re.compile(r"`((?:agent_client|protocol|sim_server)(?:\.\w+)+)`")


def documented_imports() -> list[tuple[str, str]]:
    found = set()
    for document in DOCUMENTS:
        text = document.read_text()
        for module, names in FROM_IMPORT.findall(text):
            found.update((module, name.strip()) for name in names.split(",") if name.strip())
        for dotted in DOTTED.findall(text):
            module, _, name = dotted.rpartition(".")
            found.add((module, name))
    return sorted(found)


@pytest.mark.parametrize("name", agent_client.__all__)
def test_every_top_level_name_imports(name: str) -> None:
    assert getattr(agent_client, name) is not None


def test_the_envs_import_from_the_package() -> None:
    from agent_client import RemoteEnv, RemoteParallelEnv, RemoteVectorEnv

    assert RemoteEnv.__name__ == "RemoteEnv"
    assert RemoteVectorEnv.__name__ == "RemoteVectorEnv"
    assert RemoteParallelEnv.__name__ == "RemoteParallelEnv"


def test_the_parallel_env_is_a_pettingzoo_parallel_env() -> None:
    from pettingzoo import ParallelEnv

    from agent_client import RemoteParallelEnv

    assert issubclass(RemoteParallelEnv, ParallelEnv)


def test_an_unknown_name_is_an_attribute_error() -> None:
    with pytest.raises(AttributeError, match="no_such_name"):
        agent_client.no_such_name  # noqa: B018


@pytest.mark.parametrize(("module", "name"), documented_imports())
def test_every_documented_name_imports(module: str, name: str) -> None:
    try:
        imported = importlib.import_module(f"{module}.{name}")
    except ModuleNotFoundError:
        imported = getattr(importlib.import_module(module), name)
    assert imported is not None
