"""Which cluster of field-window headings is the Earth's field (Langlotz 2011 sec. 5, the panorama's
place in the world, :mod:`.world_alignment`).

The world alignment turns each short window of field samples into the heading of the field it
implies in the panorama frame. A disturbance that turns the field while keeping its strength and
dip forms a second cluster of those headings, and nothing in one window tells it from the Earth's
field; the history does. :func:`episode_cost` scores a candidate by the disturbance episodes it
implies, :func:`choose_cluster` picks among the candidates with hysteresis. No ROS here.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .window_statistics import shorth
from .world_alignment_config import WorldAlignmentConfig

Array = NDArray[np.float64]


def episode_cost(rel: Array, centre: float, width: float, config: WorldAlignmentConfig) -> float:
    """Negative log-odds (nats, up to a constant) that the field whose window headings ``rel``
    (time order) sit at ``centre`` is the Earth's: every other window is then disturbed, each
    maximal run of them is one episode costing ``disturbance_onset_nats``, and every disturbed
    second costs 1 / ``disturbance_duration_s`` (episodes of exponentially distributed length).
    Runs shorter than ``min_episode_windows`` are noise: length only."""
    off = np.abs(rel - centre)[None, :] > config.reject_widths * width
    return _episode_costs(off, config)[0]


def _episode_costs(off: NDArray[np.bool_], config: WorldAlignmentConfig) -> list[float]:
    """:func:`episode_cost` of each row of ``off`` (candidates x windows in time order: the
    windows off that candidate), all rows in a few whole-array operations."""
    c = config
    n_off = off.sum(axis=1).tolist()
    # A run of at least m off-windows is a run of the windows that start m in a row: counting
    # the starts of those runs counts the episodes.
    long = off
    for k in range(1, c.min_episode_windows):
        long = long[:, :-1] & off[:, k:]
    if long.shape[1] == 0:  # fewer windows than an episode takes
        return [0.0 if k == 0 else k * c.window_s / c.disturbance_duration_s for k in n_off]
    starts = (long[:, 1:] & ~long[:, :-1]).sum(axis=1) + long[:, 0]
    return [0.0 if k == 0 else int(e) * c.disturbance_onset_nats + k * c.window_s / c.disturbance_duration_s
            for k, e in zip(n_off, starts.tolist())]


def choose_cluster(rel: Array, densest: float, previous: float | None, width: float,
                   config: WorldAlignmentConfig) -> tuple[float, float]:
    """The heading (in the units of ``rel``) of the window cluster taken as the Earth's field, and
    the variance (rad^2) of the doubt between it and the runner-up.

    Candidates: the densest cluster, the one the last solve chose (``previous``, None at first)
    and the densest of the windows far from those; the one with the lowest :func:`episode_cost`
    wins, the last choice keeping its place unless beaten by ``mode_switch_nats``. So a
    disturbance as long as the clean data so far takes over (the longer run is the likelier
    field), but a field the phone returns to after an episode is the Earth's at once (calling it
    disturbed would take two episodes). The candidates' deviations are one (candidates x
    windows) array that serves the far test, their support and their costs (numpy's per-call
    cost, not arithmetic, is most of a solve's)."""
    c = config
    limit = c.reject_widths * width
    candidates = [densest] if previous is None else [densest, previous]
    dev = np.abs(rel - np.array(candidates)[:, None])
    off = dev > limit
    far = off.all(axis=0)
    if int(far.sum()) >= 2:
        third = shorth(rel[far])[0]
        candidates.append(third)
        dev = np.concatenate((dev, np.abs(rel - third)[None, :]))
        off = dev > limit
    # A candidate no window supports any more (the last choice, after h moved) cannot win.
    supported = (dev <= limit).any(axis=1).tolist()
    costs = [k if ok else math.inf for k, ok in zip(_episode_costs(off, c), supported)]
    best = min(range(len(costs)), key=costs.__getitem__)  # the first of equal costs
    if previous is not None and math.isfinite(costs[1]) and costs[best] > costs[1] - c.mode_switch_nats:
        best = 1
    chosen, cost = candidates[best], costs[best]
    # The runner-up: the cheapest candidate clearly apart from the chosen one.
    rivals = [(k, x) for k, x in zip(costs, candidates) if abs(x - chosen) > limit]
    ambiguity_var = 0.0
    if rivals:
        k, x = min(rivals)
        p = 1.0 / (1.0 + math.exp(min(k - cost, 50.0)))
        ambiguity_var = p * (1.0 - p) * (x - chosen) ** 2
    return chosen, ambiguity_var
