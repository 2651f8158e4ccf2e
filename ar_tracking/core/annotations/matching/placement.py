"""Placement of the annotations by an alignment rotation (Langlotz 2011 sec. 4.3): the
:class:`Placement` and :class:`Alignment` records, the placement gate and score
(:class:`_CandidateArrays`), and the placements without an alignment."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from ...panorama.cylinder import CylinderGeometry
from .config import MatchConfig
from ..parallax import ParallaxModel
from .tiles import Candidate

Array = NDArray[np.float64]


@dataclass
class Placement:
    """Where one annotation is placed in the target panorama."""

    index: int
    u: float
    v: float
    direction: Array
    status: str  # 'matched' | 'inferred'
    score: float
    #: Shown as placed (:meth:`ReDetector.result` sets it: the alignment is supported and, for an
    #: inferred placement, pinned by matches near it); else only approximate.
    supported: bool = False
    #: Where the alignment puts the annotation (unit direction in the target panorama: the
    #: rotation, with the parallax model - leave-one-out for a matched one - when fitted); None
    #: without an alignment. A matched placement far from it is one of two disagreeing pieces
    #: of evidence (:attr:`.config.MatchConfig.matched_agreement_px`).
    predicted: Array | None = None


@dataclass
class Alignment:
    """Outcome of the alignment: R_target_source (None without a valid hypothesis)."""

    R_target_source: Array | None
    placements: list[Placement] = field(default_factory=list)
    inliers: list[int] = field(default_factory=list)
    normalised_error_px: float = float('nan')
    hypotheses: int = 0
    #: Vertical tolerance of matches when the alignment is gravity-constrained, else None.
    v_tol: float | None = None
    #: The parallax model the placements were corrected with (None: the rotation alone).
    parallax: ParallaxModel | None = None
    #: Placement gate after the parallax model (pixels; NaN: none applied).
    parallax_gate_px: float = float('nan')
    #: Placements of the landmarks (:mod:`.landmarks`; not in ``placements``).
    landmarks: list[Placement] = field(default_factory=list)
    #: Matched annotations and landmarks behind the rotation, and whether that supports showing
    #: the placements as placed (:attr:`MatchConfig.min_support_matches`); ``support_reason``
    #: says why not (one line).
    support: int = 0
    supported: bool = False
    support_reason: str = 'no alignment'
    #: Angle between the alignment and the prior rotation, rad (NaN without a prior).
    prior_correction_rad: float = float('nan')
    #: Standard deviation of the annotations' depth ratio to the parallax model
    #: (:func:`.parallax.depth_scale_sigma`; NaN: no ratio fitted).
    depth_ratio_sigma: float = float('nan')
    #: Standard deviation (rad) of the parallax model's heading at each annotation (global
    #: index; :func:`.parallax.prediction_sigma`), with ``MatchConfig.prediction_support``.
    prediction_sigma: dict[int, float] = field(default_factory=dict)


def offset_from_prediction_px(p: Placement, geometry: CylinderGeometry) -> float:
    """Map distance (px) between the placement and where the alignment puts it
    (:attr:`Placement.predicted`; inf without a prediction)."""
    if p.predicted is None:
        return math.inf
    u, v = geometry.project(p.predicted)
    return float(geometry.map_distance(p.u, p.v, u, v))


class CandidateDirections:
    """Unit directions of candidates' map positions (:meth:`CylinderGeometry.unproject`), kept
    from one alignment to the next: between two ``result`` calls the candidates of a few
    annotations change, and each call unprojected all of them three or four times. Two forms,
    each computed as before: a candidate list as one array (RANSAC's hypotheses and fits), a
    single candidate from 0-d arrays (its placement) - numpy may round the two ways differently
    in the last bit. The arrays are read-only. :meth:`next_round` forgets what the last round
    did not use."""

    def __init__(self, geometry: CylinderGeometry) -> None:
        self.geometry = geometry
        self._lists: dict[tuple[Candidate, ...], Array] = {}
        self._points: dict[tuple[float, float], Array] = {}
        self._last_lists: dict[tuple[Candidate, ...], Array] = {}
        self._last_points: dict[tuple[float, float], Array] = {}

    def next_round(self) -> None:
        """Start a round: what the round before used stays available, the rest is dropped."""
        self._last_lists, self._lists = self._lists, {}
        self._last_points, self._points = self._points, {}

    def of_list(self, candidates: Sequence[Candidate]) -> Array:
        """(k, 3) directions of a candidate list, unprojected as one array ((0, 3) for none)."""
        key = tuple(candidates)
        d = self._lists.get(key)
        if d is None:
            d = self._last_lists.get(key)
            if d is None:
                if key:
                    d = self.geometry.unproject(np.array([c.u for c in key]), np.array([c.v for c in key]))
                else:
                    d = np.zeros((0, 3))
                d.flags.writeable = False
            self._lists[key] = d
        return d

    def of(self, c: Candidate) -> Array:
        """(3,) direction of one candidate, unprojected from 0-d arrays."""
        key = (c.u, c.v)
        d = self._points.get(key)
        if d is None:
            d = self._last_points.get(key)
            if d is None:
                d = self.geometry.unproject(np.array(c.u), np.array(c.v))
                d.flags.writeable = False
            self._points[key] = d
        return d


def best_candidate_placements(candidates: Sequence[Sequence[Candidate]],
                              geometry: CylinderGeometry) -> list[Placement]:
    """Without alignment: every annotation with a candidate at its best one (sec. 3.2)."""
    out = []
    for i, cands in enumerate(candidates):
        if cands:
            c = cands[0]
            d = geometry.unproject(np.array(c.u), np.array(c.v))
            out.append(Placement(i, c.u, c.v, d, 'matched', c.score))
    return out

def place_annotations(R: Array, source_dirs: Array, candidates: Sequence[Sequence[Candidate]],
                      config: MatchConfig | None = None, geometry: CylinderGeometry | None = None,
                      v_tol: float | None = None, predicted: Array | None = None,
                      directions: CandidateDirections | None = None,
                      arrays: _CandidateArrays | None = None) -> list[Placement]:
    """Every annotation placed by the rotation R (sec. 4.3): at its candidate within
    ``placement_px`` of where R puts it with the best NCC minus ``placement_penalty`` x
    distance / ``placement_px`` (matched; the NCC, not the prior-penalised score: the rotation
    supersedes the compass), or, with none there, at that position (inferred). ``v_tol``: a
    candidate further above or below than this is none (``gravity_v_px``). ``predicted`` (n, 3):
    the directions to use instead of R's (the rotation with the parallax model); ``directions``:
    the candidates' directions kept from earlier calls (default: computed here); ``arrays``: the
    same candidates with the same ``v_tol`` as :class:`_CandidateArrays`, when the caller has
    them (RANSAC)."""
    cfg = config or MatchConfig()
    geo = geometry or CylinderGeometry()
    dirs = directions if directions is not None else CandidateDirections(geo)
    src = np.asarray(source_dirs, float).reshape(-1, 3)
    pred = src @ np.asarray(R, float).T if predicted is None else np.asarray(predicted, float)
    with_c = [i for i in range(len(src)) if candidates[i]]
    best: dict[int, int] = {}
    if with_c:
        cs = arrays if arrays is not None else _CandidateArrays(candidates, with_c, v_tol)
        assert cs.with_c == with_c and cs.v_tol == v_tol
        value = cs.values(cs.distances_from(pred[with_c][None], geo)[0], cfg)
        best = {i: int(np.argmax(value[r])) for r, i in enumerate(with_c) if np.isfinite(value[r]).any()}
    out = []
    for i in range(len(src)):
        if i in best:
            c = candidates[i][best[i]]
            out.append(Placement(i, c.u, c.v, dirs.of(c), 'matched', c.ncc,
                                 predicted=pred[i]))
        else:
            pu, pv = geo.project(pred[i])
            out.append(Placement(i, float(pu), float(pv), pred[i], 'inferred', float('nan'), predicted=pred[i]))
    return out


class _CandidateArrays:
    """The candidates of the annotations ``with_c`` as padded (n_c, k) arrays (NaN: none)."""

    def __init__(self, candidates: Sequence[Sequence[Candidate]], with_c: list[int],
                 v_tol: float | None = None) -> None:
        self.with_c = with_c
        self.v_tol = v_tol
        k_max = max(len(candidates[i]) for i in with_c)
        self.U = np.full((len(with_c), k_max), np.nan)
        self.V = np.full((len(with_c), k_max), np.nan)
        self.NCC = np.full((len(with_c), k_max), np.nan)
        for r, i in enumerate(with_c):
            m = len(candidates[i])
            self.U[r, :m] = [c.u for c in candidates[i]]
            self.V[r, :m] = [c.v for c in candidates[i]]
            self.NCC[r, :m] = [c.ncc for c in candidates[i]]

    def distances(self, Rs: Array, src: Array, geo: CylinderGeometry) -> Array:
        """(H, n_c, k) map distances between where each rotation puts each annotation and its
        candidates (NaN for missing candidates, inf beyond ``v_tol`` above or below)."""
        return self.distances_from(np.einsum('hij,nj->hni', Rs.reshape(-1, 3, 3), src[self.with_c]), geo)

    def distances_from(self, dirs: Array, geo: CylinderGeometry) -> Array:
        """(H, n_c, k) map distances from predicted directions (H, n_c, 3) to the candidates."""
        pu, pv = geo.project(dirs)
        du = geo.column_distance(pu[:, :, None], self.U[None])
        dv = pv[:, :, None] - self.V[None]
        dist = np.hypot(du, dv)
        if self.v_tol is not None:
            with np.errstate(invalid='ignore'):
                dist[np.abs(dv) > self.v_tol] = np.inf
        return dist

    def values(self, dd: Array, cfg: MatchConfig) -> Array:
        """Placement value of each candidate at distances ``dd`` (..., n_c, k): its NCC minus
        ``placement_penalty`` x distance / ``placement_px``; -inf outside the gate
        (max(placement_px, inlier_px); beyond ``v_tol``, inf distances) or without a candidate."""
        gate = max(cfg.placement_px, cfg.inlier_px)
        with np.errstate(invalid='ignore'):
            value = np.where(dd < gate, self.NCC - cfg.placement_penalty * dd / cfg.placement_px, -np.inf)
        value[np.isnan(value)] = -np.inf  # (nan_to_num would make -inf finite too)
        return value

    def placement_score(self, dd: Array, cfg: MatchConfig) -> Array:
        """(H,) placement score of each rotation: the sum over the annotations of the best
        placement value (:meth:`values`), 0 without a candidate in the gate. It counts the
        annotations the rotation explains, like the inliers, weighted by how well they match;
        the normalised error alone prefers a rotation that lines up look-alikes one repetition
        away (repeated facades) over the true one, whose near anchors are shifted by parallax."""
        return np.maximum(self.values(dd, cfg).max(axis=2), 0.0).sum(axis=1)
