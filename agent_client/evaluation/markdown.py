"""``report.md`` from `agent_client.evaluation.report.build_metrics`' dictionary.

One function per section; each returns its lines. The text only formats numbers of the
dictionary (``metrics.json``), the paper's among them, so the two never disagree.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from agent_client.constants import HEADWAY_SAFE, JERK_COMFORT_LIMIT, TTC_CRITICAL
from agent_client.evaluation.evaluate import ROLE_LABELS
from agent_client.evaluation.paper import LC_FLOW_PER_LANE, NGSIM_FLOW_PER_LANE

Figures = dict[str, Any]
"""One driver's figures (`agent_client.evaluation.summaries.summarise`, with its spec)."""


def _f(value: Any, digits: int = 2, suffix: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f}{suffix}"


def _pct(value: Any, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{100 * value:.{digits}f} %"


def _gain(value: float | None) -> str:
    """A relative gain as a signed percentage ("+1.2 %")."""
    return f"{100 * value:+.1f} %" if value is not None else "n/a"


def _ratio_gain(ratio: float | None) -> str:
    """The gain of a ratio over 1 ("+1.2 %" for 1.012)."""
    return _gain(ratio - 1) if ratio is not None else "n/a"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return lines


def render_markdown(metrics: dict[str, Any]) -> str:
    """The report as markdown, from `build_metrics`' dictionary."""
    lines = _setting_section(metrics)
    lines += _cf_section(metrics)
    lines += _safety_section(metrics)
    if metrics["lane_changing"] is not None:
        lines += _lc_section(metrics)
    else:
        lines += [
            "## Lane changing (Tables 2-3, Fig. 13)",
            "",
            "Not applicable: the scenario has one lane (evaluate on `cflc` for these tables).",
            "",
        ]
    lines += _route_section(metrics)
    lines += _trajectory_section(metrics)
    lines += [
        f"Every figure above is in `metrics.json`. Paper: {metrics['paper']['source']}.",
        "",
    ]
    return "\n".join(lines)


def _setting_section(metrics: dict[str, Any]) -> list[str]:
    """Title, scenario, seeds, versions and the command that reruns the evaluation."""
    drivers = metrics["drivers"]
    title = f"# Evaluation on `{metrics['scenario']}`: `{drivers['policy']['spec']}` vs "
    title += f"`{drivers['baseline']['spec']}`"
    seeds = metrics["seeds"]
    seed_text = f"{seeds[0]}..{seeds[-1]}" if len(seeds) > 1 else str(seeds[0])
    options = ", ".join(f"{k}={v}" for k, v in metrics["options"].items()) or "defaults"
    return [
        title,
        "",
        "## Setting and how to rerun",
        "",
        f"* scenario `{metrics['scenario']}` ({metrics['lanes']} lane(s)), options: {options}",
        f"* {metrics['episodes']} episodes per driver, the same seeds for all: {seed_text}",
        *(f"* {name}: {value}" for name, value in metrics["versions"].items()),
        "",
        "```",
        metrics["command"],
        "```",
        "",
    ]


# --------------------------------------------------------------------------- car following


def _cf_section(metrics: dict[str, Any]) -> list[str]:
    """Figs. 9-10: the car-following table, the gain, the ceiling, the targets and the plots."""
    drivers = metrics["drivers"]
    paper = metrics["paper"]["cf"]
    header = ["figure", *(f"{ROLE_LABELS[r]} (`{d['spec']}`)" for r, d in drivers.items()), "paper"]
    gain = _ratio_gain(metrics["comparison"]["speed_ratio_policy_to_baseline"])
    lines = ["## Car following: efficiency, comfort, safety (Figs. 9-10)", ""]
    lines += _table(header, _cf_rows(list(drivers.values()), paper))
    lines += [
        "",
        f"Policy vs baseline average speed: **{gain}** (the paper: DRL "
        f"{paper['drl_average_speed']} m/s vs IDM {paper['idm_average_speed']} m/s, "
        f"{_gain(paper['drl_gain_over_idm'])}).",
        "",
        _ceiling_note(metrics),
        "",
        _targets_line(metrics["comparison"]["targets"]),
        "",
    ]
    return lines + _cf_figures(metrics)


def _cf_rows(drivers: list[Figures], paper: dict[str, Any]) -> list[list[str]]:
    """One row per car-following figure: its name, each driver's value, the paper's."""
    rows: list[tuple[str, Callable[[Figures], str], str]] = [
        ("average speed, m/s: mean (sd)",
         lambda d: f"{_f(d['average_speed'])} ({_f(d['average_speed_sd'])})",
         f"DRL {paper['drl_average_speed']}, IDM {paper['idm_average_speed']}"),
        ("leader-at-entry ceiling, m/s (mean)", lambda d: _f(d["ceiling_speed"]), ""),
        ("average speed / ceiling (mean of episodes)",
         lambda d: _f(d["speed_ratio_to_ceiling"], 3), "not reported"),
        ("collisions per episode (episodes with one)",
         lambda d: f"{_f(d['collisions_per_episode'])} ({d['episodes_with_collision']})", ""),
        ("red lights passed per episode (episodes with one)",
         lambda d: f"{_f(d.get('red_lights_per_episode', 0.0))} "
                   f"({d.get('episodes_with_red_light', 0)})", ""),
        (f"jerk samples above {JERK_COMFORT_LIMIT} m/s^3",
         lambda d: _pct(d["jerk_share_above_limit"], 2),
         f"DRL {_pct(paper['drl_jerk_share_above_limit'])}"),
        ("max abs jerk, m/s^3", lambda d: _f(d["max_abs_jerk"]), ""),
        (f"time headway < {HEADWAY_SAFE:g} s (share)",
         lambda d: _pct(d["headway"]["share_below_1s"]), ""),
        ("time headway, s: mean / median",
         lambda d: f"{_f(d['headway']['mean'])} / {_f(d['headway']['median'])}", ""),
        ("min time headway, s", lambda d: _f(d["min_time_headway"]), ""),
        ("min TTC, s", lambda d: _f(d["ttc"]["min"]), ""),
        (f"TTC < {TTC_CRITICAL:g} s (share of leader steps)",
         lambda d: _pct(d["ttc"]["share_below_4s"]), ""),
        ("end reasons",
         lambda d: ", ".join(f"{k} {v}" for k, v in d["end_reasons"].items()), ""),
    ]  # fmt: skip
    return [[name, *(cell(d) for d in drivers), theirs] for name, cell, theirs in rows]


def _ceiling_note(metrics: dict[str, Any]) -> str:
    """What the leader-at-entry ceiling means here: a bound on one lane, a reference on more,
    or nothing where the server reported none (on a ring nobody arrives)."""
    ratio = metrics["comparison"]["ceiling_over_baseline"]
    if ratio is None:
        return (
            "**The ceiling.** The server reported no leader-at-entry trip (a scenario without "
            "arrivals, such as the ring, or `report_ceiling` off): compare the speeds with the "
            "baseline's only."
        )
    ceiling = _ratio_gain(ratio)
    if metrics["multi_lane"]:
        return (
            "The ceiling is the average speed the ego would have had arriving together with the "
            "vehicle ahead of it at entry. On several lanes the ego can overtake that vehicle, so "
            f"here it is a reference, not a bound (it is {ceiling} over the baseline)."
        )
    paper_gain = _gain(metrics["paper"]["cf"]["drl_gain_over_idm"])
    return (
        "**The ceiling.** On one lane the ego cannot arrive before the vehicle that was ahead "
        "of it when it entered, and that vehicle's trip does not depend on the ego: arriving "
        f"together with it is the best any driver can do here, {ceiling} over the "
        f"baseline on these seeds. A gain like the paper's {paper_gain} over IDM is therefore out "
        "of reach without collisions (or a baseline far below the traffic's pace): judge a "
        "speed gain against the ceiling, not against the paper's figure."
    )


def _targets_line(targets: dict[str, bool]) -> str:
    return (
        "Targets of the training's greedy evaluations (docs/learner.md), for the policy: "
        + ", ".join(f"{name} {'yes' if ok else 'no'}" for name, ok in targets.items())
        + "."
    )


def _cf_figures(metrics: dict[str, Any]) -> list[str]:
    """Figs. 9 and 10 with their captions."""
    figures = metrics["figures"]
    paper_share = _pct(metrics["paper"]["cf"]["drl_jerk_share_above_limit"])
    return [
        f"![Fig. 9: per-episode average speed]({figures['speed_distribution']})",
        "",
        "Fig. 9 (ours): per-episode average speed of each driver on the same seeds; dashed "
        "lines are the means, the dotted line the mean leader-at-entry ceiling.",
        "",
        f"![Fig. 10: distribution of jerk]({figures['jerk_distribution']})",
        "",
        f"Fig. 10 (ours): jerk at the simulator's step (change of the realised acceleration over "
        f"one step), all steps of all episodes; the dashed lines mark +/-{JERK_COMFORT_LIMIT} "
        f"m/s^3, the paper's comfort limit ({paper_share} of its DRL samples were beyond it).",
        "",
    ]


# --------------------------------------------------------------------------- lane changing


def _lc_section(metrics: dict[str, Any]) -> list[str]:
    """Tables 2-3 and Fig. 13: lane changes over training, in evaluation, their gaps, the gain."""
    drivers = metrics["drivers"]
    paper = metrics["paper"]["lc"]
    lc = metrics["lane_changing"]
    return [
        "## Lane changing (Tables 2-3, Fig. 13)",
        "",
        *_table2_section(lc["table2"], paper["table2_last_row"]),
        "",
        *_evaluation_lc_section(drivers, paper),
        "",
        *_table3_section(drivers, paper["table3"]),
        "",
        *_integrated_vs_cf_section(lc["integrated_vs_cf"], paper),
        "",
    ]


def _table2_section(table: dict[str, Any] | None, last: dict[str, Any]) -> list[str]:
    """Table 2: lane-change instructions, success and frequency per range of training episodes."""
    lines = ["### Table 2: lane-change decisions over training", ""]
    if table is None:
        return [*lines, "Not computed: pass `--run runs/NAME` to read the run's `episodes.csv`."]
    rows = [
        [
            row["episodes"],
            _f(row["instructions_per_episode"], 1),
            _pct(row["success_rate"]),
            _f(row["reward_of_successful_lc"], 3),
            _f(row["frequency"]),
        ]
        for row in table["rows"]
    ]
    rows.append(
        [
            f"paper {last['episodes']}",
            str(last["instructions_per_episode"]),
            _pct(last["success_rate"]),
            _f(last["reward_of_successful_lc"]),
            _f(last["lc_frequency"]),
        ]
    )
    header = [
        "training episodes",
        "LC instructions per episode",
        "success rate (started / instructions)",
        "avg. reward of successful LC",
        "actual LC frequency (veh/km/lane)",
    ]
    return [
        *lines,
        f"From `{table['run']}/episodes.csv`, {table['lanes']} lanes.",
        "",
        *_table(header, rows),
        "",
        "Instructions are lane changes started plus refused (any reason: gap too small, no "
        "lane, one already in progress). The reward of a successful lane change is the "
        "training reward of the step whose instruction started it (n/a: no change in the "
        "range, or a log without that column).",
    ]


def _evaluation_lc_section(drivers: dict[str, Figures], paper: dict[str, Any]) -> list[str]:
    """Each driver's lane changes in the evaluation episodes, beside the paper's and NGSIM's."""
    rows = [_lc_row(ROLE_LABELS[role], d["lane_changes"]) for role, d in drivers.items()]
    rows.append(["paper (converged)", "", "", "", _f(paper["lc_frequency"])])
    ngsim = paper["lc_frequency_ngsim"]
    rows += [[f"NGSIM {name}", "", "", "", _f(value)] for name, value in ngsim.items()]
    header = ["driver", "instructions per episode", "success rate", "refused by reason"]
    flows = " and ".join(str(flow) for flow in NGSIM_FLOW_PER_LANE.values())
    return [
        "### Lane changes in the evaluation episodes",
        "",
        *_table([*header, "veh/km/lane"], rows),
        "",
        "Frequency = lane changes started / (km driven x lanes). NGSIM's traffic was heavier "
        f"(about {flows} veh/h/lane) than the paper's {LC_FLOW_PER_LANE} veh/h/lane.",
    ]


def _lc_row(label: str, stats: dict[str, Any]) -> list[str]:
    refused = ", ".join(f"{k} {v}" for k, v in stats["refused_by_reason"].items()) or "none"
    if stats.get("aborted"):
        refused += f"; started but aborted by the simulator: {stats['aborted']}"
    return [
        label,
        _f(stats["instructions_per_episode"], 1),
        _pct(stats["success_rate"]),
        refused,
        _f(stats["frequency"]),
    ]


def _table3_section(drivers: dict[str, Figures], paper: dict[str, Any]) -> list[str]:
    """Table 3: target-lane lead and lag time headways at lane-change starts."""
    rows = [[name, _f(value["lead"]), _f(value["lag"]), ""] for name, value in paper.items()]
    for role, d in drivers.items():
        t3 = d["table3"]
        samples = f"{t3['lane_changes']} (lead {t3['lead_samples']}, lag {t3['lag_samples']})"
        rows.append([f"ours: {ROLE_LABELS[role]}", _f(t3["lead"]), _f(t3["lag"]), samples])
    header = ["", "avg. lead time headway (s)", "avg. lag time headway (s)"]
    return [
        "### Table 3: time headways in the target lane when a lane change starts",
        "",
        *_table([*header, "lane changes (samples)"], rows),
        "",
        "Lead (lag) headway: gap to the leader (follower) in the target lane at the observation "
        "before the lane change started, divided by the ego's speed; a lane without that vehicle "
        "gives no sample.",
    ]


def _integrated_vs_cf_section(versus: dict[str, Any] | None, paper: dict[str, Any]) -> list[str]:
    """Fig. 13: the integrated (CF + LC) policy's average speed against a CF-only policy's."""
    lines = ["### The integrated model against car following only (Fig. 13)", ""]
    if versus is None:
        return [*lines, "Not computed: pass `--cf-policy FILE` (a car-following-only policy)."]
    rows = [
        [
            "ours",
            _f(versus["integrated_average_speed"]),
            _f(versus["cf_average_speed"]),
            _gain(versus["gain"]),
        ],
        [
            "paper",
            _f(paper["integrated_average_speed"]),
            _f(paper["cf_average_speed"]),
            _gain(paper["integrated_gain_over_cf"]),
        ],
    ]
    header = ["", "integrated (CF + LC), m/s", "CF only, m/s", "gain"]
    return [
        *lines,
        *_table(header, rows),
        "",
        "Fig. 9 above shows the CF-only policy's speed distribution too.",
    ]


# --------------------------------------------------------------------------- the route

_ROUTE_ROWS: tuple[tuple[str, str, str], ...] = (
    ("reached the end of the route", "arrival_share", "pct"),
    ("stood at a lane end (`lane_end`)", "lane_end_share", "pct"),
    ("route changes per episode", "route_changes_per_episode", "f2"),
    ("median distance to the lane end at the change (m)", "median_lane_end_at_change", "f0"),
    ("shortest distance to the lane end at a change (m)", "min_lane_end_at_change", "f0"),
    ("median time of the change after the hand-over (s)", "median_time_of_change", "f1"),
    ("median gap accepted to the new leader (s)", "median_lead_headway", "f2"),
    ("median gap accepted from the new follower (s)", "median_lag_headway", "f2"),
    ("shortest gap from the new follower (m)", "min_lag_gap", "f1"),
    ("median braking imposed on the new follower (m/s²)", "median_follower_braking", "f2"),
    ("hardest braking imposed on the new follower (m/s²)", "max_follower_braking", "f2"),
    ("minimum PET, SSM device (s)", "min_pet", "f2"),
)
"""The route table's rows: label, key of `routes.route_figures`, format."""


def _route_cell(value: Any, kind: str) -> str:
    if value is None:
        return "-"
    if kind == "pct":
        return _pct(value)
    return f"{value:.{kind[1]}f}"


def _route_section(metrics: dict[str, Any]) -> list[str]:
    """Merges, exits and lane drops: arrivals, where and into which gap each driver changed
    towards its route, the braking it imposed, and the picture of one change."""
    drivers = {r: d for r, d in metrics["drivers"].items() if d.get("route")}
    if not drivers:
        return []
    header = ["figure", *(f"{ROLE_LABELS[r]} (`{d['spec']}`)" for r, d in drivers.items())]
    rows = [
        [label, *(_route_cell(d["route"][key], kind) for d in drivers.values())]
        for label, key, kind in _ROUTE_ROWS
    ]
    lines = ["## The route: merges, exits, lane drops", ""]
    lines += _table(header, rows)
    lines += [
        "",
        "A route change is a lane change started towards a lane that leads on along the route "
        "(`road.lanes_to_change`, docs/protocol.md §4.9); its gaps are those of the target lane "
        "when it started, in seconds of the ego's speed; the braking imposed is the new "
        "follower's hardest deceleration in the 5 s after the change completed. The same seeds "
        "for every driver.",
        "",
    ]
    plan = metrics["figures"].get("route_change")
    if plan:
        lines += [
            f"![route change, seed {plan['seed']}]({plan['file']})",
            "",
            f"Seed {plan['seed']}: each driver's first route change, along the road from the end "
            "of the lane it left (red dashed line); the ego thick black, the vehicles of the "
            "lane it moved to coloured by their speed; the triangle marks where the change "
            "started, the dotted line when it completed.",
            "",
        ]
    return lines


# --------------------------------------------------------------------------- chosen episodes


def _trajectory_section(metrics: dict[str, Any]) -> list[str]:
    """Time series and time-space diagrams of the chosen episodes (docs/evaluation.md)."""
    plan = metrics["figures"].get("trajectories") or []
    lines = ["## Trajectories of chosen episodes", ""]
    if not plan:
        return [*lines, "No episode traces in these records: nothing to draw.", ""]
    lines += [
        "The first seed and the policy's most critical episode (a collision, else the smallest "
        "minimum TTC, else the smallest minimum time headway), unless `--trajectory-seeds` "
        "chose others. docs/evaluation.md explains how to read the pictures.",
        "",
    ]
    for entry in plan:
        seed = entry["seed"]
        lines += [
            f"### Seed {seed}: {entry['why']}",
            "",
            f"![time series, seed {seed}]({entry['time_series']})",
            "",
            "Speed, gap to the leader, acceleration and jerk of each driver on this seed over the "
            f"time since the episode's start; dashed: the speed limit and +/-{JERK_COMFORT_LIMIT} "
            "m/s^3; dotted verticals: lane changes started, in the driver's colour.",
            "",
        ]
        for role, name in entry["time_space"].items():
            lines += [f"![time-space diagram: {ROLE_LABELS[role]}, seed {seed}]({name})", ""]
        lines += [
            "Time-space diagrams, one row per lane (leftmost on top): along the road (left) and "
            "from the ego's front (right); the ego is the thick black line in its lane, the "
            "neighbours it observed are coloured by their speed; purple triangles and dashed "
            "(dotted) verticals mark its lane changes started (completed), a red X a collision.",
            "",
        ]
    return lines


_SAFETY_ROWS: tuple[tuple[str, str, str], ...] = (
    ("conflicts per km", "conflicts_per_km", "f2"),
    ("episodes with a conflict", "episodes_with_conflict", "d"),
    ("conflicts with min TTC < 1.5 s", "critical_conflicts", "d"),
    ("minimum TTC (s)", "min_ttc", "f2"),
    ("median of the conflicts' minimum TTC (s)", "median_conflict_min_ttc", "f2"),
    ("time exposed, TTC < 3 s (s per km)", "ttc_exposed_s_per_km", "f2"),
    ("time exposed (% of driving time)", "ttc_exposed_share", "pct"),
    ("time-integrated TTC (s² per km)", "ttc_integral_per_km", "f2"),
    ("maximum DRAC (m/s²)", "max_drac", "f2"),
    ("DRAC > 3 m/s² (s per km)", "drac_beyond_s_per_km", "f2"),
    ("minimum PET (s)", "min_pet", "f2"),
)
"""The safety table's rows: label, key of `safety.safety_figures`, format."""


def _safety_cell(value: Any, kind: str) -> str:
    if value is None:
        return "-"
    if kind == "pct":
        return _pct(value, 2)
    return str(value) if kind == "d" else _f(value)


def _safety_section(metrics: dict[str, Any]) -> list[str]:
    """SUMO's surrogate safety measures of every driver on the same seeds, or why there are none."""
    drivers = {r: d for r, d in metrics["drivers"].items() if d.get("safety")}
    lines = ["## Surrogate safety measures (SUMO's SSM device)", ""]
    if not drivers:
        why = "Not reported: the server's scenario offers no `ssm` option (docs/protocol.md §4.7)."
        return [*lines, why, ""]
    header = ["measure", *(f"{ROLE_LABELS[r]} (`{d['spec']}`)" for r, d in drivers.items())]
    rows = [
        [label, *(_safety_cell(d["safety"][key], kind) for d in drivers.values())]
        for label, key, kind in _SAFETY_ROWS
    ]
    lines += _table(header, rows)
    thresholds = next(iter(drivers.values()))["safety"]["thresholds"]
    lines += [
        "",
        f"A conflict is an encounter of the ego with another vehicle in which TTC fell below "
        f"{thresholds['ttc_s']:g} s, DRAC rose above {thresholds['drac']:g} m/s² or PET fell below "
        f"{thresholds['pet_s']:g} s, as SUMO's SSM device measures them at every simulation step "
        "(SUMO's default thresholds); a minimum TTC under 1.5 s is serious (Van der Horst 1991). "
        "PET is defined for crossing and merging paths only, so it is rarely set on a straight "
        "road. The same seeds for every driver.",
        "",
    ]
    figure = metrics["figures"].get("safety")
    if figure:
        lines += [f"![surrogate safety measures]({figure})", ""]
    else:
        lines += ["No driver had a conflict on these seeds: there is no distribution to draw.", ""]
    return lines
