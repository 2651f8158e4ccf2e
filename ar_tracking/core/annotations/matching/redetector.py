"""The re-detection scheduler (Langlotz 2011 sec. 3.2, 6.1): the queue of finished tiles and
the per-frame budget, the guided re-detection and the parallax model after the alignment, the
support test, and the choice between several source panoramas near one GPS fix."""
from __future__ import annotations

import math
from collections import deque
from dataclasses import replace
from typing import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from ...rotations import trace_angle
from ...panorama.cylinder import CylinderGeometry
from .config import MatchConfig
from ..parallax import ParallaxModel, fit_parallax
from .placement import Alignment, Placement, best_candidate_placements, place_annotations
from .alignment import ransac_alignment
from .tiles import Candidate, CandidateList, TileMatcher

Array = NDArray[np.float64]


def expected_positions(source_dirs: Array, R_enu_source: Sequence[Array | None],
                       R_enu_target: Array, geometry: CylinderGeometry) -> Array:
    """(n, 2) expected map positions of the annotations in the target panorama from the
    absolute orientations of both panoramas (sec. 4.2); NaN where the source's is unknown."""
    out = np.full((len(source_dirs), 2), np.nan)
    for i, (d, R) in enumerate(zip(source_dirs, R_enu_source)):
        if R is not None:
            u, v = geometry.project(R_enu_target.T @ (R @ d))
            out[i] = (float(u), float(v))
    return out


class ReDetector:
    """Matching state of one browsing panorama against a set of annotations.

    The annotations may come from several source panoramas (``groups``: one id per
    annotation); matching runs on all of them, the alignment per group, and :meth:`result`
    gives the group whose annotations score best (sec. 6.1). Newly finished tiles go into a
    FIFO (:meth:`add_finished_tiles`), :meth:`step` does at most ``max_ops`` tile x annotation
    comparisons (the per-frame budget of sec. 3.2).

    ``landmark`` flags the patches that are landmarks of their source panorama
    (:mod:`.landmarks`): matched and aligned like annotations, but not placed for the user and
    not counted in the group's score; their placements are in ``Alignment.landmarks``."""

    def __init__(self, patches: Sequence[NDArray[np.uint8]], source_dirs: Array,
                 groups: Sequence[str], config: MatchConfig | None = None,
                 geometry: CylinderGeometry | None = None,
                 R_enu_source: Sequence[Array | None] | None = None,
                 landmark: Sequence[bool] | None = None,
                 source_heading_sigma_rad: Sequence[float] | None = None) -> None:
        self.config = cfg = config or MatchConfig()
        self.geometry = geo = geometry or CylinderGeometry()
        self.source_dirs = np.asarray(source_dirs, float).reshape(-1, 3)
        n = len(self.source_dirs)
        self.groups = list(groups)
        self.landmark = np.zeros(n, bool) if landmark is None else np.asarray(landmark, bool).reshape(n)
        self.R_enu_source = list(R_enu_source) if R_enu_source is not None else [None] * n
        self.source_sigma = (np.full(n, np.nan) if source_heading_sigma_rad is None
                             else np.asarray(source_heading_sigma_rad, float).reshape(n))
        self.target_sigma = float('nan')
        # One TileMatcher per patch size.
        self.matchers: list[tuple[TileMatcher, list[int]]] = []
        for side in sorted({p.shape[0] for p in patches}):
            ids = [i for i, p in enumerate(patches) if p.shape[0] == side]
            self.matchers.append((TileMatcher([patches[i] for i in ids], cfg, geo), ids))
        #: annotation index -> its patch (float32, as matched), for the guided re-detection
        self._patches: dict[int, NDArray[np.float32]] = {
            i: matcher.patches[k] for matcher, ids in self.matchers for k, i in enumerate(ids)}
        self.candidates = [CandidateList(cfg.candidates, cfg.min_separation_px, geo.width) for _ in range(n)]
        self.queue: deque[int] = deque()
        self.seen: set[int] = set()
        self.expected_uv: Array | None = None
        self.R_enu_target: Array | None = None
        self.dirty = False
        self.tiles_done = 0
        self._cache: tuple[str | None, Alignment] | None = None
        self._map: tuple[NDArray[np.float32], NDArray[np.bool_] | None] | None = None

    @property
    def n(self) -> int:
        return len(self.source_dirs)

    def add_finished_tiles(self, tiles: NDArray) -> int:
        """Queue the finished tiles (mono8 tile image, >0 finished) not seen before."""
        new = [int(t) for t in np.flatnonzero(np.asarray(tiles).reshape(-1) > 0) if int(t) not in self.seen]
        self.seen.update(new)
        self.queue.extend(new)
        return len(new)

    def set_orientation(self, R_enu_target: Array | None, heading_sigma_rad: float = float('nan')) -> None:
        """The browsing panorama's absolute orientation (R_enu_panorama) for the prior, with the
        1-sigma of its heading when known (for the support test)."""
        self.R_enu_target = None if R_enu_target is None else np.asarray(R_enu_target, float)
        if math.isfinite(heading_sigma_rad) != math.isfinite(self.target_sigma) or (
                math.isfinite(heading_sigma_rad) and abs(heading_sigma_rad - self.target_sigma) > 1e-9):
            self._cache = None
        self.target_sigma = float(heading_sigma_rad)
        if R_enu_target is None or not self.config.sensor_prior:
            self.expected_uv = None
        else:
            self.expected_uv = expected_positions(self.source_dirs, self.R_enu_source,
                                                  np.asarray(R_enu_target, float), self.geometry)

    def step(self, gray: NDArray[np.float32], mapped: NDArray[np.bool_] | None, max_ops: int | None = None) -> int:
        """Match queued tiles until ``max_ops`` tile x annotation comparisons are done (at
        least one tile); returns the number of tiles processed."""
        self._map = (gray, mapped)
        done = ops = 0
        while self.queue and (max_ops is None or ops < max_ops or done == 0):
            tile = self.queue.popleft()
            for matcher, ids in self.matchers:
                exp = self.expected_uv[ids] if self.expected_uv is not None else None
                found = matcher.match_tile(gray, mapped, tile, None, exp)
                ops += len(ids)
                for k, cands in found.items():
                    for c in cands:
                        if self.candidates[ids[k]].add(c):
                            self.dirty = True
            done += 1
        self.tiles_done += done
        if done:
            self._cache = None if self.dirty else self._cache
        return done

    def _guided(self, p: Placement, predicted: tuple[float, float] | None = None,
                v_tol: float | None = None, config: MatchConfig | None = None) -> None:
        """Guided re-detection around where the alignment puts an annotation (``predicted``,
        default the placement itself, i.e. an inferred one): NCC in a +-``placement_px``
        window (+-``v_tol`` vertically after a gravity-constrained alignment), minus
        ``guided_penalty`` x distance / ``placement_px``; the best position with an NCC of at
        least ``guided_min_ncc`` becomes the placement when its penalised score beats that of
        the current match (an inferred placement has none)."""
        cfg, geo = config or self.config, self.geometry
        cu, cv_ = predicted if predicted is not None else (p.u, p.v)
        win = self._window_ncc(p.index, cu, cv_, cfg.placement_px, v_tol)
        if win is None:
            return
        res, xs, ys, inside = win
        dist = np.hypot(xs[None, :], ys[:, None])
        score = np.where(inside, res - cfg.guided_penalty * dist / cfg.placement_px, -np.inf)
        y, x = np.unravel_index(int(np.argmax(score)), score.shape)
        if res[y, x] < cfg.guided_min_ncc:
            return
        if p.status == 'matched':
            d_now = float(geo.map_distance(np.array(p.u), np.array(p.v), cu, cv_))
            if score[y, x] <= p.score - cfg.guided_penalty * d_now / cfg.placement_px + 1e-6:
                return
        p.u = float((cu + xs[x]) % geo.width)
        p.v = float(cv_ + ys[y])
        p.direction = geo.unproject(np.array(p.u), np.array(p.v))
        p.status = 'matched'
        p.score = float(res[y, x])

    def _window_ncc(self, index: int, cu: float, cv_: float, radius_px: float, v_tol: float | None
                    ) -> tuple[NDArray[np.float32], Array, Array, NDArray[np.bool_]] | None:
        """NCC (TM_CCOEFF_NORMED) of patch ``index`` at every position within ``radius_px`` of
        (cu, cv_) (and ``v_tol`` above or below): (ncc, column offsets, row offsets from (cu, cv_),
        inside mask); positions not fully mapped get -1. None without a map, outside the rows or
        for an unknown index."""
        if self._map is None:
            return None
        gray, mapped = self._map
        patch = self._patches.get(index)
        if patch is None:
            return None
        P = patch.shape[0]
        r = int(math.ceil(radius_px))
        rv = r if v_tol is None else int(math.ceil(min(v_tol, radius_px)))
        x0 = int(round(cu - (P - 1) / 2)) - r
        y0 = int(round(cv_ - (P - 1) / 2)) - rv
        if y0 < 0 or y0 + P + 2 * rv > gray.shape[0]:
            return None
        # The window's columns (wrapping at the map's seam: gathered, else a slice - same pixels).
        cols: slice | Array = slice(x0, x0 + P + 2 * r)
        if x0 < 0 or x0 + P + 2 * r > self.geometry.width:
            cols = np.arange(x0, x0 + P + 2 * r) % self.geometry.width
        reg = gray[y0:y0 + P + 2 * rv][:, cols].astype(np.float32)
        if mapped is not None:
            m = mapped[y0:y0 + P + 2 * rv][:, cols].astype(np.float32)
            full = cv2.boxFilter(m, -1, (P, P), anchor=(0, 0), normalize=True,
                                 borderType=cv2.BORDER_CONSTANT)[:2 * rv + 1, :2 * r + 1]
        else:
            full = np.ones((2 * rv + 1, 2 * r + 1), np.float32)
        res: NDArray[np.float32] = np.asarray(
            cv2.matchTemplate(reg, patch, cv2.TM_CCOEFF_NORMED), np.float32)
        res[(full < 0.999) | ~np.isfinite(res)] = -1.0
        # Offsets from the predicted position (sub-pixel: x0, y0 were rounded).
        c = (P - 1) / 2.0
        xs: Array = x0 + c + np.arange(2 * r + 1, dtype=float) - cu
        ys: Array = y0 + c + np.arange(2 * rv + 1, dtype=float) - cv_
        inside: NDArray[np.bool_] = (np.hypot(xs[None, :], ys[:, None]) <= radius_px) & (
            np.abs(ys)[:, None] <= (v_tol if v_tol is not None else np.inf))
        return res, xs, ys, inside

    def _lookalike(self, p: Placement, predicted: Array, v_tol: float | None, gate_px: float) -> None:
        """The look-alike test of a matched placement (:attr:`MatchConfig.lookalike_margin`):
        another local NCC maximum (3 x 3) inside the gate around its prediction, at least
        ``lookalike_sep_px`` from the match, with an NCC within the margin of the match's makes
        the placement the prediction itself (inferred)."""
        cfg, geo = self.config, self.geometry
        cu, cv_ = (float(x) for x in geo.project(predicted))
        win = self._window_ncc(p.index, cu, cv_, gate_px, v_tol)
        if win is None:
            return
        res, xs, ys, inside = win
        peak = (res >= cv2.dilate(res, np.ones((3, 3), np.uint8))) & inside & (res > -1.0)
        far = geo.map_distance(cu + xs[None, :], cv_ + ys[:, None], p.u, p.v) >= cfg.lookalike_sep_px
        rivals = res[peak & far]
        # The match's own NCC on the current map (the candidate's may be from an earlier map).
        own = res[inside & ~far]
        score = float(own.max()) if own.size else p.score
        if rivals.size == 0 or float(rivals.max()) < score - cfg.lookalike_margin:
            return
        p.u, p.v = cu, cv_
        p.direction = np.asarray(predicted, float).copy()
        p.status = 'inferred'
        p.score = float('nan')

    def _finish(self, al: Alignment, ids: list[int], cands: list[list[Candidate]]) -> None:
        """Make the placements' indices global and re-detect them guided; with a gravity-
        constrained alignment and enough matches, the parallax model: fitted on the matches,
        then every annotation placed and guided again around its corrected position."""
        cfg, geo = self.config, self.geometry
        R = al.R_target_source
        src = self.source_dirs[ids]
        predicted = None if R is None else src @ R.T
        self._guide_all(al.placements, ids, predicted, al.v_tol)
        matched = [ids.index(p.index) for p in al.placements if p.status == 'matched']
        up = self._up()
        if (R is None or al.v_tol is None or up is None or not cfg.parallax_model
                or len(matched) < cfg.parallax_min_matches):
            return
        assert predicted is not None  # R is set
        found = {p.index: p.direction for p in al.placements}
        observed = np.array([found[ids[k]] for k in matched])

        def fit(rows: Array | slice) -> ParallaxModel:
            return fit_parallax(predicted[matched][rows], observed[rows], up, cfg.parallax_sigma_match,
                                cfg.parallax_sigma, cfg.parallax_trim_sigmas)

        model = fit(slice(None))
        corrected = model.apply(predicted)
        # A matched annotation's own position comes from the others only (leave-one-out): a
        # look-alike match must not pull the prediction it is judged against towards itself.
        for r, k in enumerate(matched):
            corrected[k] = fit(np.arange(len(matched)) != r).apply(predicted[k])[0]
        post = cfg
        if cfg.parallax_gate_sigmas > 0:
            al.parallax_gate_px = self._parallax_gate(corrected[matched], observed)
            post = replace(cfg, placement_px=al.parallax_gate_px)
        al.placements = place_annotations(R, src, cands, post, geo, al.v_tol, predicted=corrected)
        al.parallax = model
        self._guide_all(al.placements, ids, corrected, al.v_tol, post)
        if cfg.lookalike_margin > 0:
            local = {i: k for k, i in enumerate(ids)}
            for p in al.placements:
                if p.status == 'matched' and not self.landmark[p.index]:
                    self._lookalike(p, corrected[local[p.index]], al.v_tol, post.placement_px)

    def _parallax_gate(self, predicted: Array, observed: Array) -> float:
        """Placement gate after the parallax model (``parallax_gate_sigmas``): that many robust
        standard deviations (1.4826 x median absolute) of the horizontal distances between the
        matches and their leave-one-out predictions, clipped to [inlier_px, placement_px]."""
        cfg, geo = self.config, self.geometry
        du = geo.column_distance(geo.project(predicted)[0], geo.project(observed)[0])
        scale = 1.4826 * float(np.median(du))
        return float(np.clip(cfg.parallax_gate_sigmas * scale, cfg.inlier_px, cfg.placement_px))

    def _guide_all(self, placements: list[Placement], ids: list[int], predicted: Array | None,
                   v_tol: float | None, config: MatchConfig | None = None) -> None:
        """Placement indices from the group's (local) to the annotations' (``ids``), then the
        guided re-detection (``guided_search``) of inferred placements and, with ``guided_all``,
        of matched ones around their ``predicted`` direction (local order); ``config`` (default
        the detector's) sets the window."""
        cfg = config or self.config
        for p in placements:
            local = p.index
            p.index = ids[local]
            if not cfg.guided_search:
                continue
            if p.status == 'inferred':
                self._guided(p, v_tol=v_tol, config=cfg)
            elif cfg.guided_all and predicted is not None:
                u, v = self.geometry.project(predicted[local])
                self._guided(p, (float(u), float(v)), v_tol, cfg)

    def _support(self, al: Alignment, ids: list[int]) -> None:
        """Whether the alignment supports showing its placements (:attr:`MatchConfig.min_support_matches`)."""
        cfg = self.config
        al.support = sum(p.status == 'matched' for p in al.placements + al.landmarks)
        al.supported = False
        if al.R_target_source is None:
            al.support_reason = 'no alignment'
            return
        if al.support < cfg.min_support_matches:
            al.support_reason = f'{al.support} matches (fewer than {cfg.min_support_matches})'
            return
        R_prior = self._prior_rotation(ids)
        if R_prior is not None:
            al.prior_correction_rad = float(trace_angle(R_prior.T @ al.R_target_source))
            sigma = math.hypot(float(self.source_sigma[ids[0]]), self.target_sigma)
            limit = cfg.support_prior_sigmas * sigma + cfg.inlier_px / self.geometry.f
            if math.isfinite(sigma) and al.prior_correction_rad > limit and al.support < cfg.strong_support_matches:
                al.support_reason = (f'{math.degrees(al.prior_correction_rad):.1f} deg from the sensor prior '
                                     f'(> {math.degrees(limit):.1f}) with {al.support} matches')
                return
        al.supported = True
        al.support_reason = ''
        matched = [p for p in al.placements + al.landmarks if p.status == 'matched']
        mu = np.array([p.u for p in matched])
        local = bool(self.landmark[ids].any())  # the local tests need landmarks' density
        W = self.geometry.width
        for p in al.placements:
            near = int(np.sum(self.geometry.column_distance(mu, p.u) <= cfg.local_support_px)) if len(mu) else 0
            if not local:
                p.supported = True
            elif p.status == 'matched':
                p.supported = not cfg.local_support_matched or near - 1 >= cfg.local_support_matches
            else:
                p.supported = near >= cfg.local_support_matches
                if not p.supported and cfg.bracket_support_px > 0 and len(mu):
                    du = (mu - p.u + W / 2) % W - W / 2  # signed column offsets of the matches
                    p.supported = bool(((du < 0) & (du >= -cfg.bracket_support_px)).any()
                                       and ((du > 0) & (du <= cfg.bracket_support_px)).any())

    def _up(self) -> Array | None:
        """The up direction (ENU z) in the browsing panorama's frame, None without its orientation."""
        return None if self.R_enu_target is None else self.R_enu_target[2].copy()

    def _prior_rotation(self, ids: list[int]) -> Array | None:
        """R_target_source from the absolute orientations of both panoramas (sec. 4.2), None
        without the sensor prior or either orientation."""
        R_src = self.R_enu_source[ids[0]] if ids else None
        if not self.config.sensor_prior or self.R_enu_target is None or R_src is None:
            return None
        return self.R_enu_target.T @ np.asarray(R_src, float)

    def result(self) -> tuple[str | None, Alignment]:
        """(source panorama id, alignment/placements) of the best-scoring group."""
        if self._cache is not None and not self.dirty:
            return self._cache
        self.dirty = False
        best: tuple[float, str | None, Alignment] = (-1.0, None, Alignment(None))
        for g in dict.fromkeys(self.groups):
            ids = [i for i, gi in enumerate(self.groups) if gi == g]
            cands = [self.candidates[i].items for i in ids]
            shown = [c for i, c in zip(ids, cands) if not self.landmark[i]]
            if not shown:
                continue
            score = float(np.mean([c[0].ncc if c else 0.0 for c in shown]))
            if score <= best[0]:
                continue
            if self.config.ransac:
                al = ransac_alignment(self.source_dirs[ids], cands, self.config, self.geometry,
                                      R_prior=self._prior_rotation(ids), up=self._up())
                if al.R_target_source is None:
                    al.placements = best_candidate_placements(cands, self.geometry)
            else:
                al = Alignment(None, best_candidate_placements(cands, self.geometry))
            self._finish(al, ids, cands)
            al.landmarks = [p for p in al.placements if self.landmark[p.index]]
            al.placements = [p for p in al.placements if not self.landmark[p.index]]
            self._support(al, ids)
            best = (score, g, al)
        self._cache = (best[1], best[2])
        return self._cache
