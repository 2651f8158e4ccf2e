"""Global alignment of the source and the target panorama (Langlotz 2011 sec. 4.3, Fig. 5):
generate rotation hypotheses (pairs of matches, or headings about gravity), score them against
every annotation's candidates, select the winner (normalised error or placement score, with the
compass prior), refine it by least squares; :func:`ransac_alignment` ties the steps together."""
from __future__ import annotations

import itertools
import math
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from ...rotations import align_about_axis, align_directions, rotations_about_axis, trace_angle
from ...panorama.cylinder import CylinderGeometry
from .config import MatchConfig
from .placement import Alignment, CandidateDirections, _CandidateArrays, place_annotations
from .tiles import Candidate

Array = NDArray[np.float64]


def absolute_orientation(a: Array, b: Array, weights: Array | None = None) -> Array:
    """The rotation R minimising sum w |R a_i - b_i|^2 for unit vectors (n >= 2, 3)
    (the absolute orientation of two sets of directions, Horn 1987; core.rotations)."""
    return align_directions(a, b, weights)

def ransac_alignment(source_dirs: Array, candidates: Sequence[Sequence[Candidate]],
                     config: MatchConfig | None = None, geometry: CylinderGeometry | None = None,
                     rng: np.random.Generator | None = None, R_prior: Array | None = None,
                     up: Array | None = None, directions: CandidateDirections | None = None) -> Alignment:
    """Global rotation between the source and the target panorama (sec. 4.3; module docstring).

    ``source_dirs`` (n, 3): unit vectors of the annotations in the source panorama;
    ``candidates[i]``: candidates of annotation i in the target map (best first). All pairs of
    annotations and candidates are tried when there are at most ``max_hypotheses`` of them,
    else that many random ones (seeded). A hypothesis is valid with more than
    ``min_inlier_ratio`` inliers; among the valid ones the lowest normalised error wins (the
    paper) or, with ``consensus_score``, the highest placement score (:func:`placement_score`).
    The winner is refined by least squares on all its matches (:func:`absolute_orientation`).

    ``R_prior`` (R_target_source from the absolute orientations, with ``prior_alignment``):
    hypotheses further than ``prior_window_px`` from it are not valid, and when none is valid
    the annotations are placed by ``R_prior`` itself (refined on the matches it explains).
    ``up`` (unit up direction in the target panorama, with ``gravity_alignment``): the rotations
    are ``R_prior`` followed by a rotation about ``up`` only, hypotheses come from single
    matches and pairs (:func:`_heading_hypotheses`) and refinements fit the heading alone.
    ``directions``: the candidates' directions kept from earlier calls (default: computed here)."""
    cfg = config or MatchConfig()
    geo = geometry or CylinderGeometry()
    dirs = directions if directions is not None else CandidateDirections(geo)
    src = np.asarray(source_dirs, float).reshape(-1, 3)
    n = len(src)
    with_c = [i for i in range(n) if candidates[i]]
    # Candidate directions and positions, per annotation.
    cu = [np.array([c.u for c in candidates[i]]) for i in range(n)]
    cv_ = [np.array([c.v for c in candidates[i]]) for i in range(n)]
    cd = [dirs.of_list(candidates[i]) for i in range(n)]
    if R_prior is not None and cfg.prior_alignment:
        R_prior = np.asarray(R_prior, float)
    else:
        R_prior = None
    k_up = v_tol = None
    if R_prior is not None and up is not None and cfg.gravity_alignment:
        k_up = np.asarray(up, float) / np.linalg.norm(up)
        v_tol = cfg.gravity_v_px
    cs = _CandidateArrays(candidates, with_c, v_tol) if with_c else None

    def fit(a: Array, b: Array) -> Array:
        """Least-squares rotation mapping directions a onto b (the heading only, with gravity)."""
        if k_up is None:
            return absolute_orientation(a, b)
        assert R_prior is not None  # k_up is only set with a prior
        return rotations_about_axis(k_up, align_about_axis(a @ R_prior.T, b, k_up))[0] @ R_prior

    def fallback() -> Alignment:
        return _prior_alignment(R_prior, src, candidates, cs, cd, cfg, geo, fit, v_tol, dirs)

    result = Alignment(None)
    if len(with_c) < max(2, cfg.min_inliers):
        return fallback()
    assert cs is not None  # with_c is not empty
    tol_rad = cfg.inlier_px / geo.f
    prior_tol = cfg.prior_window_px / geo.f  # the compass error, rad
    need = max(cfg.min_inliers, int(math.floor(cfg.min_inlier_ratio * len(with_c))) + 1)
    if k_up is not None:
        assert R_prior is not None  # k_up is only set with a prior
        Rs = _heading_hypotheses(src, with_c, cd, R_prior, k_up, tol_rad, prior_tol)
    else:
        Rs = _pair_hypotheses(src, with_c, candidates, cd, cfg, tol_rad, rng)
        if R_prior is not None and len(Rs):
            Rs = Rs[trace_angle(R_prior.T @ Rs) <= prior_tol]
    if not len(Rs):
        return fallback()
    result.hypotheses = len(Rs)
    # Every hypothesis against every annotation's candidates at once.
    dd = cs.distances(Rs, src, geo)  # (H, n_c, k)
    dist = _nearest(dd)  # (H, n)
    inl_h = dist < cfg.inlier_px  # (H, n) inliers of each hypothesis
    n_inl = inl_h.sum(axis=1)
    valid = n_inl >= need
    if not valid.any():
        return fallback()
    nerr = np.where(valid, np.where(inl_h, dist, 0.0).sum(axis=1) / np.maximum(n_inl, 1), np.inf)
    if cfg.consensus_score:
        # Highest placement score wins; among equal scores, the lower normalised error.
        gain = np.where(valid, cs.placement_score(dd, cfg), -np.inf)
        if R_prior is not None:
            # The compass as one more vote: prior_penalty per annotation at the window's edge.
            gain = gain - cfg.prior_penalty * len(with_c) * trace_angle(R_prior.T @ Rs) / prior_tol
        h = int(np.lexsort((np.round(nerr, 9), -np.round(gain, 9)))[0])
    else:
        # Lowest normalised error wins; among equal errors, more inliers.
        h = int(np.lexsort((-n_inl, np.round(nerr, 9)))[0])
    best = (float(nerr[h]), Rs[h], [with_c[r] for r in np.flatnonzero(inl_h[h])])
    R = best[1]
    if cfg.consensus_score:
        R = _refine_on_placements(R, src, cs, cd, geo, cfg, need, fit)
    else:
        # Refine on all inliers (their nearest candidates), then score once more.
        for _ in range(2):
            a_in, b_in = [], []
            for i in _score(R, src, with_c, cu, cv_, geo, cfg.inlier_px)[0]:
                k = _consistent(R, src[i], candidates[i], cu[i], cv_[i], geo, cfg.inlier_px)
                a_in.append(src[i])
                b_in.append(cd[i][k])
            if len(a_in) >= 2:
                R_new = fit(np.array(a_in), np.array(b_in))
                if len(_score(R_new, src, with_c, cu, cv_, geo, cfg.inlier_px)[0]) >= len(a_in):
                    R = R_new
    inl, err = _score(R, src, with_c, cu, cv_, geo, cfg.inlier_px)
    if len(inl) < need:
        R, inl, err = best[1], best[2], best[0] * len(best[2])
    result.R_target_source = R
    result.inliers = inl
    result.normalised_error_px = err / len(inl)
    result.placements = place_annotations(R, src, candidates, cfg, geo, v_tol, directions=dirs, arrays=cs)
    result.v_tol = v_tol
    return result


def _nearest(dd: Array) -> Array:
    """(H, n) distance of each annotation's nearest candidate under each hypothesis from the
    (H, n, k) distances: ``np.nanmin`` over the last axis (NaN: no candidate), as a chain of
    ``np.fmin`` over the k slices - the same values (a minimum rounds nothing) without the
    reduction's cost along an axis of 3."""
    out = dd[..., 0].copy()
    for j in range(1, dd.shape[-1]):
        np.fmin(out, dd[..., j], out=out)
    return out


def _pair_hypotheses(src: Array, with_c: list[int], candidates: Sequence[Sequence[Candidate]],
                     cd: list[Array], cfg: MatchConfig, tol_rad: float,
                     rng: np.random.Generator | None) -> Array:
    """(H, 3, 3) rotation hypotheses of sec. 4.3: every pair of annotations and one candidate
    of each (at most ``max_hypotheses``, drawn with a seeded generator), the least-squares
    rotation of the two vector pairs (absolute orientation: it maps the bisector and the normal
    of (a1, a2) onto those of (b1, b2)); pairs closer than 2 deg or whose angles differ by more
    than two inlier tolerances make none."""
    pairs = [(i, j, a, b) for i, j in itertools.combinations(with_c, 2)
             for a in range(len(candidates[i])) for b in range(len(candidates[j]))]
    if len(pairs) > cfg.max_hypotheses:
        rng = rng or np.random.default_rng(cfg.seed)
        pairs = [pairs[k] for k in rng.choice(len(pairs), cfg.max_hypotheses, replace=False)]
    P = np.array(pairs, dtype=np.int64)
    a1, a2 = src[P[:, 0]], src[P[:, 1]]
    b1 = np.array([cd[i][k] for i, k in zip(P[:, 0], P[:, 2])])
    b2 = np.array([cd[j][k] for j, k in zip(P[:, 1], P[:, 3])])
    ang_a = np.arccos(np.clip(np.einsum('ij,ij->i', a1, a2), -1, 1))
    ang_b = np.arccos(np.clip(np.einsum('ij,ij->i', b1, b2), -1, 1))
    ok = (ang_a >= math.radians(2.0)) & (ang_b >= math.radians(2.0)) & (np.abs(ang_a - ang_b) <= 2 * tol_rad)
    return _frames(b1[ok], b2[ok]) @ np.swapaxes(_frames(a1[ok], a2[ok]), 1, 2)


def _heading_hypotheses(src: Array, with_c: list[int], cd: list[Array], R_prior: Array,
                        up: Array, tol_rad: float, prior_tol: float) -> Array:
    """(H, 3, 3) gravity-constrained hypotheses ``R(up, psi) @ R_prior``: psi from every single
    match and the least-squares psi of every pair of matches of two annotations. A match whose
    elevation differs from the prior's prediction by more than ``tol_rad`` makes none (the tilt
    is known), nor does a psi beyond the compass error ``prior_tol``; headings are merged on a
    grid of ``tol_rad`` / 100."""
    rows = [(i, k) for i in with_c for k in range(len(cd[i]))]
    a = src[[i for i, _ in rows]] @ R_prior.T
    b = np.array([cd[i][k] for i, k in rows])
    elev_a = np.arcsin(np.clip(a @ up, -1, 1))
    elev_b = np.arcsin(np.clip(b @ up, -1, 1))
    ok = np.abs(elev_a - elev_b) <= tol_rad
    ann = np.array([i for i, _ in rows])[ok]
    # psi = atan2(sum of sine parts, sum of cosine parts) for one match or a pair (align_about_axis).
    sin_p = np.einsum('ij,ij->i', b[ok], np.cross(up, a[ok]))
    cos_p = np.einsum('ij,ij->i', b[ok], a[ok]) - (b[ok] @ up) * (a[ok] @ up)
    r1, r2 = np.triu_indices(len(ann), 1)
    two = ann[r1] != ann[r2]
    psi = np.concatenate([np.arctan2(sin_p, cos_p),
                          np.arctan2(sin_p[r1[two]] + sin_p[r2[two]], cos_p[r1[two]] + cos_p[r2[two]])])
    psi = psi[np.abs(psi) <= prior_tol]
    # Headings closer than a hundredth of the inlier tolerance (0.1 px) are one hypothesis: with
    # landmarks (tens of matches, hundreds of pairs) most pairs repeat another's heading, and
    # the winner is refined by least squares anyway.
    step = tol_rad / 100.0
    psi = np.unique(np.round(psi / step)) * step
    return rotations_about_axis(up, psi) @ R_prior


def _prior_alignment(R_prior: Array | None, src: Array, candidates: Sequence[Sequence[Candidate]],
                     cs: _CandidateArrays | None, cd: list[Array], cfg: MatchConfig,
                     geo: CylinderGeometry,
                     fit: Callable[[Array, Array], Array] = absolute_orientation,
                     v_tol: float | None = None, directions: CandidateDirections | None = None) -> Alignment:
    """The alignment when RANSAC finds no valid hypothesis: with a prior rotation, the
    annotations placed by it after a least-squares refinement on the matches it explains (two
    at least; kept only within the compass error of the prior); without one, nothing."""
    if R_prior is None:
        return Alignment(None)
    R = R_prior
    if cs is not None:
        R = _refine_on_placements(R_prior, src, cs, cd, geo, cfg, 2, fit)
        if float(trace_angle(R_prior.T @ R)) > cfg.prior_window_px / geo.f:
            R = R_prior
    placements = place_annotations(R, src, candidates, cfg, geo, v_tol, directions=directions, arrays=cs)
    return Alignment(R, placements, [p.index for p in placements if p.status == 'matched'], v_tol=v_tol)

def _refine_on_placements(R: Array, src: Array, cs: _CandidateArrays, cd: list[Array],
                          geo: CylinderGeometry, cfg: MatchConfig, need: int,
                          fit: Callable[[Array, Array], Array] = absolute_orientation) -> Array:
    """Least-squares rotation (absolute orientation) on all matched annotations, each one's
    candidate chosen as in :func:`place_annotations`, repeated (at most ``refine_iterations``
    times) while the choice stays the same or the placement score grows. The minimal pair of
    the hypothesis carries the parallax and localisation error of two annotations only; the
    least squares over all matches averages them (the score, a sum of distances, may then drop
    a little: the choice of candidates decides)."""
    def choice(dd: Array) -> tuple[list[int], list[int], float]:
        value = cs.values(dd, cfg)
        rows = [int(r) for r in np.flatnonzero(np.isfinite(value).any(axis=1))]
        return rows, [int(np.argmax(value[r])) for r in rows], float(cs.placement_score(dd[None], cfg)[0])

    rows, ks, score = choice(cs.distances(R[None], src, geo)[0])
    for _ in range(cfg.refine_iterations):
        if len(rows) < max(2, need):
            break
        a = src[[cs.with_c[r] for r in rows]]
        b = np.array([cd[cs.with_c[r]][k] for r, k in zip(rows, ks)])
        R_new = fit(a, b)
        rows_new, ks_new, score_new = choice(cs.distances(R_new[None], src, geo)[0])
        same = rows_new == rows and ks_new == ks
        if not (same or score_new > score):
            break
        R, rows, ks, score = R_new, rows_new, ks_new, score_new
        if same:
            break
    return R


def _consistent(R: Array, a: Array, cands: Sequence[Candidate], cu: Array, cv_: Array,
                geo: CylinderGeometry, inlier_px: float, penalty: float = 0.0) -> int:
    """Index of the candidate within ``inlier_px`` of where R puts ``a`` with the best score
    minus ``penalty`` x distance / ``inlier_px`` (the nearest one when none is): parallax
    between the two standing points shifts the prediction by a few pixels, so the nearest
    candidate is not always the right one, nor is the best-scoring one (repeated facades)."""
    pu, pv = geo.project(R @ a)
    dist = geo.map_distance(cu, cv_, pu, pv)
    near = np.flatnonzero(dist < inlier_px)
    if near.size == 0:
        return int(np.argmin(dist))
    return int(near[np.argmax([cands[int(k)].score - penalty * dist[k] / inlier_px for k in near])])


def _frames(v1: Array, v2: Array) -> Array:
    """(H, 3, 3) orthonormal frames [bisector, normal, bisector x normal] of vector pairs."""
    m = v1 + v2
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    n = np.cross(v1, v2)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.stack([m, n, np.cross(m, n)], axis=2)


def _score(R: Array, src: Array, with_c: list[int], cu: list[Array], cv_: list[Array],
           geo: CylinderGeometry, inlier_px: float) -> tuple[list[int], float]:
    pu, pv = geo.project(src[with_c] @ R.T)
    inl, err = [], 0.0
    for k, i in enumerate(with_c):
        dmin = float(np.min(geo.map_distance(cu[i], cv_[i], pu[k], pv[k])))
        if dmin < inlier_px:
            inl.append(i)
            err += dmin
    return inl, err
