"""Judging drivers: metrics, the evaluation against a baseline and its report, IDM calibration.

`metrics` (one episode, `aggregate` over several), `evaluate` (driving the compared drivers),
`summaries` (a driver's figures, Tables 2-3), `report` with `markdown` and `plots` (the output),
`paper` (the published figures), `targets` (the acceptance criteria), `calibration` (IDM fitted
to the simulator's human drivers).
"""
