"""Measurement and keyframe culling (Klein & Murray 2009 sec. 3.2, 3.3).

Bundle adjustment cost grows with the measurements per point T (the O(N T^2) reduced-system
outer products) and with the keyframes M (the O(M^3) reduced-camera solve), so the mapper keeps
both small:

* sec. 3.2, measurement culling: a point's information matrix (H&Z A6.6 notation) is
  ``V = sum_j V_j``, ``V_j = w_j B_j^T Sigma_j^-1 B_j`` with ``B_j`` the 2x3 projection Jacobian
  w.r.t. the point in keyframe j, ``Sigma_j = (2**level)^2 I`` and ``w_j`` the Tukey weight from
  the last bundle adjustment. ``m_j = |V| - |V - V_j|`` is the information lost without
  measurement j; a point measured by more than 8 keyframes keeps only its 8 most useful.
* sec. 3.3, keyframe culling: points vote for the keyframes they find useful. A keyframe that is
  one of only two observers gets 0.5; with ``o > 2`` observers the keyframe ranked ``rank`` by
  ``m_j`` (1 = most useful) gets ``(o_hat - (rank - 1)) / sum_{i=1..o_hat} i`` with
  ``o_hat = min(o, 4)`` (ranks beyond ``o_hat`` get 0). Once more than 35 keyframes are active,
  the keyframe with the lowest summed utility is erased if that utility is also below a fixed
  threshold; the fixed first keyframe is never erased.

The functions here decide; the mapper applies the decisions to the :class:`SlamMap`.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from .bundle_adjustment import point_jacobians
from .camera import Camera
from .slam_map import Keyframe

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: Sec. 3.2: measurements kept per point.
MAX_MEASUREMENTS_PER_POINT = 8
#: Sec. 3.3: culling starts when more keyframes than this are active.
MAX_KEYFRAMES = 35
#: Sec. 3.3 "fixed threshold" on a keyframe's summed utility (not given in the paper). One point
#: voting for a keyframe is worth between 0.1 (4th of >= 4 observers) and 0.5 (one of two), so a
#: keyframe under 4.0 contributes about what 8-40 points' weakest measurements do: redundant.
KEYFRAME_UTILITY_THRESHOLD = 4.0


@dataclass
class InformationTable:
    """Per-measurement information metrics of a set of keyframes and points (sec. 3.2).

    Arrays are aligned per measurement: ``kf_ids``, ``point_ids``, ``m`` (= |V| - |V - V_j|),
    ``n_obs`` (observers of that measurement's point).
    """

    kf_ids: NDArray[np.int64]
    point_ids: NDArray[np.int64]
    m: Array
    n_obs: NDArray[np.int64]


def point_measurement_metrics(xyz: Array, poses: Sequence[tuple[Array, Array]],
                              sigmas_px: Array, weights: Array, camera: Camera) -> Array:
    """``m_j = |V| - |V - V_j|`` for one point (3,) measured in keyframes ``poses`` (sec. 3.2)."""
    xyz = np.asarray(xyz, float).reshape(1, 3)
    Vj = np.zeros((len(poses), 3, 3))
    for j, (R, t) in enumerate(poses):
        B = point_jacobians(camera, R, t, xyz)[0]
        Vj[j] = float(weights[j]) / float(sigmas_px[j]) ** 2 * (B.T @ B)
    V = Vj.sum(axis=0)
    return np.linalg.det(V) - np.linalg.det(V[None] - Vj)


def information_table(keyframes: Iterable[Keyframe], points: Mapping[int, Array], camera: Camera,
                      weights: Mapping[tuple[int, int], float] | None = None) -> InformationTable:
    """Vectorised :func:`point_measurement_metrics` over all measurements of ``points`` made by
    the non-erased ``keyframes``; ``weights`` (kf id, point id) -> M-estimator weight (default 1).
    """
    kf_list = [kf for kf in keyframes if not kf.erased]
    pids_all = sorted(int(p) for p in points)
    ppos = {p: i for i, p in enumerate(pids_all)}
    P = np.array([np.asarray(points[p], float) for p in pids_all]).reshape(-1, 3)
    kf_col, pt_col, V_list = [], [], []
    for kf in kf_list:
        pids = [pid for pid in kf.measurements if pid in ppos]
        if not pids:
            continue
        idx = np.array([ppos[p] for p in pids], np.int64)
        B = point_jacobians(camera, kf.R_c_w, kf.t_c_w, P[idx])
        s2 = np.array([kf.measurements[p].sigma_px ** 2 for p in pids])
        w = np.ones(len(pids)) if weights is None else np.array(
            [float(weights.get((kf.id, p), 1.0)) for p in pids])
        V_list.append((w / s2)[:, None, None] * np.einsum('nji,njk->nik', B, B))
        kf_col.append(np.full(len(pids), kf.id, np.int64))
        pt_col.append(idx)
    if not V_list:
        e = np.zeros(0, np.int64)
        return InformationTable(e, e.copy(), np.zeros(0), e.copy())
    Vj = np.concatenate(V_list)
    pt_idx = np.concatenate(pt_col)
    V = np.zeros((len(pids_all), 3, 3))
    np.add.at(V, pt_idx, Vj)
    m = np.linalg.det(V[pt_idx]) - np.linalg.det(V[pt_idx] - Vj)
    n_obs = np.bincount(pt_idx, minlength=len(pids_all))[pt_idx]
    return InformationTable(np.concatenate(kf_col), np.array(pids_all, np.int64)[pt_idx], m,
                            n_obs.astype(np.int64))


def _groups(table: InformationTable) -> dict[int, NDArray[np.int64]]:
    """Point id -> indices of its measurements in ``table``."""
    order = np.argsort(table.point_ids, kind='stable')
    pids = table.point_ids[order]
    cuts = np.flatnonzero(np.diff(pids)) + 1
    return {int(pids[g[0]]): order[g] for g in np.split(np.arange(len(pids)), cuts) if len(g)}


def measurements_to_cull(keyframes: Iterable[Keyframe], points: Mapping[int, Array], camera: Camera,
                         weights: Mapping[tuple[int, int], float] | None = None,
                         max_per_point: int = MAX_MEASUREMENTS_PER_POINT
                         ) -> list[tuple[int, int]]:
    """Sec. 3.2: (kf id, point id) of the measurements beyond each point's ``max_per_point``
    most useful ones (largest ``m_j``)."""
    table = information_table(keyframes, points, camera, weights)
    out: list[tuple[int, int]] = []
    for pid, idx in _groups(table).items():
        if len(idx) <= max_per_point:
            continue
        order = idx[np.argsort(-table.m[idx], kind='stable')]
        out.extend((int(table.kf_ids[i]), pid) for i in order[max_per_point:])
    return out


def rank_utilities(m: Array) -> Array:
    """Sec. 3.3 votes of one point for its ``o = len(m)`` observers (aligned with ``m``)."""
    o = len(m)
    if o < 2:
        return np.zeros(o)
    if o == 2:
        return np.full(2, 0.5)
    o_hat = min(o, 4)
    denom = o_hat * (o_hat + 1) / 2.0
    u = np.zeros(o)
    order = np.argsort(-np.asarray(m, float), kind='stable')
    for rank, j in enumerate(order[:o_hat], start=1):
        u[j] = (o_hat - (rank - 1)) / denom
    return u


def keyframe_utilities(keyframes: Iterable[Keyframe], points: Mapping[int, Array], camera: Camera,
                       weights: Mapping[tuple[int, int], float] | None = None) -> dict[int, float]:
    """Sec. 3.3: summed point votes per non-erased keyframe (0 for keyframes without points)."""
    kf_list = [kf for kf in keyframes if not kf.erased]
    util = {kf.id: 0.0 for kf in kf_list}
    table = information_table(kf_list, points, camera, weights)
    for idx in _groups(table).values():
        u = rank_utilities(table.m[idx])
        for i, ui in zip(idx, u):
            util[int(table.kf_ids[i])] += float(ui)
    return util


def keyframes_to_cull(keyframes: Iterable[Keyframe], points: Mapping[int, Array], camera: Camera,
                      weights: Mapping[tuple[int, int], float] | None = None,
                      max_keyframes: int = MAX_KEYFRAMES,
                      utility_threshold: float = KEYFRAME_UTILITY_THRESHOLD,
                      max_erase: int = 1, protected: Iterable[int] = ()) -> list[int]:
    """Sec. 3.3: ids of keyframes to erase, lowest summed utility first.

    Only while more than ``max_keyframes`` keyframes are active, at most ``max_erase``, never a
    ``fixed`` keyframe or one in ``protected`` (e.g. the newest), and only if its utility is below
    ``utility_threshold``. Utilities are recomputed after each (simulated) erasure, since losing
    a keyframe raises the value of the remaining observers of its points.
    """
    active = [kf for kf in keyframes if not kf.erased]
    protected = set(protected)
    out: list[int] = []
    while len(active) > max_keyframes and len(out) < max_erase:
        util = keyframe_utilities(active, points, camera, weights)
        cands = [(u, k) for k, u in util.items() if k not in protected
                 and not next(kf for kf in active if kf.id == k).fixed]
        if not cands:
            break
        u_min, k_min = min(cands)
        if u_min >= utility_threshold:
            break
        logger.debug('keyframe %d culled: utility %.2f', k_min, u_min)
        out.append(k_min)
        active = [kf for kf in active if kf.id != k_min]
    return out


__all__ = ['InformationTable', 'point_measurement_metrics', 'information_table',
           'measurements_to_cull', 'rank_utilities', 'keyframe_utilities', 'keyframes_to_cull',
           'MAX_MEASUREMENTS_PER_POINT', 'MAX_KEYFRAMES', 'KEYFRAME_UTILITY_THRESHOLD']
