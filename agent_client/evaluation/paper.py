"""The paper's published figures, shown beside ours in every evaluation report.

Ye, Zhang and Sun, *Automated vehicle's behavior decision making using deep reinforcement
learning and high-fidelity simulation environment*: car following in §4.4 (Figs. 9-10), lane
changing in §4.5 (Tables 2-3, Fig. 13). `PAPER` goes into ``metrics.json`` as it is.
"""

from __future__ import annotations

from typing import Any

SOURCE = "Ye, Zhang and Sun, §4.4-4.5, Figs. 9-10 and 13, Tables 2-3"
"""Where the figures below come from."""

DRL_JERK_SHARE_ABOVE_LIMIT = 0.026
"""Share of the paper's DRL jerk samples above 5.6 m/s^3 (Fig. 10); also a training target."""

PAPER: dict[str, Any] = {
    "source": SOURCE,
    "cf": {
        "drl_average_speed": 12.44,
        "idm_average_speed": 11.53,
        "drl_gain_over_idm": 0.079,
        "drl_jerk_share_above_limit": DRL_JERK_SHARE_ABOVE_LIMIT,
    },
    "lc": {
        "integrated_average_speed": 12.74,
        "cf_average_speed": 12.44,
        "integrated_gain_over_cf": 0.024,
        "lc_frequency": 0.81,
        "lc_frequency_ngsim": {"US-101": 0.63, "I-80": 0.80},
        "table3": {
            "US-101": {"lead": 2.78, "lag": 3.14},
            "I-80": {"lead": 1.49, "lag": 1.71},
            "DRL-LC": {"lead": 4.70, "lag": 4.81},
        },
        "table2_last_row": {
            "episodes": "10000-11000",
            "instructions_per_episode": 16,
            "success_rate": 0.043,
            "reward_of_successful_lc": 6.50,
            "lc_frequency": 0.69,
        },
    },
}
"""The figures (m/s, shares, veh/km/lane, s) by section: ``cf`` (§4.4) and ``lc`` (§4.5)."""

NGSIM_FLOW_PER_LANE = {"US-101": 1600, "I-80": 1300}
"""veh/h/lane, about: the traffic of the NGSIM data the paper's lane changes are compared with."""
LC_FLOW_PER_LANE = 700
"""veh/h/lane: the traffic of the paper's lane-changing experiments."""
