"""Build the built-in SUMO scenarios (netconvert) into the scenario cache.

Run at image build time so that a container's first reset of ``cf``, ``cflc`` or ``ring`` with
default options reuses these files instead of running netconvert. Other traffic options
(``--option flow=...``) still build their own folder on first use, as outside a container.

Usage: python prebuild_scenarios.py [CACHE_DIR]   (default: the server's own default cache)
"""

from __future__ import annotations

import sys
from pathlib import Path

from sim_server.backends.sumo.scenarios import BUILTIN_SCENARIOS, default_cache_dir


def main(argv: list[str]) -> int:
    cache_dir = Path(argv[0]) if argv else default_cache_dir()
    for scenario in BUILTIN_SCENARIOS.values():
        config = scenario.build(dict(scenario.info().options), cache_dir)
        print(f"prebuilt {scenario.name}: {config}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
