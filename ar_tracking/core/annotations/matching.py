"""Re-detection of annotations in a new panorama map (Langlotz 2011 sec. 3.2, 4.2, 4.3).

* :class:`TileMatcher` (sec. 3.2): the patches of the annotations are matched against one
  finished tile of the map at a time, each tile once. A Walsh-transform pre-check comes first:
  the low-sequency Walsh-Hadamard coefficients of the patch (4 x 4 blocks of block means, DC
  dropped, normalised, which makes them invariant to gain and offset) are compared with those
  of every patch position of the tile, for all annotations in one matrix product; only positions
  and annotations that pass ``walsh_min`` get normalised cross-correlation (NCC). The three best
  candidates per annotation are kept (:class:`CandidateList`).
* Sensor prior (sec. 4.2): with the expected map position of an annotation from the absolute
  orientation, the search is limited to a window of +-``prior_window_px`` (the compass error:
  10 deg = 57 px) around it, and a window three times larger is searched with the NCC score
  penalised by the distance from the inner window, so matches outside the inner window count
  only when they are very good.
* :func:`ransac_alignment` (sec. 4.3, Fig. 5): RANSAC over pairs of annotations and one of
  their candidates; each hypothesis is the rotation that best aligns the two pairs of unit
  vectors (absolute orientation, :func:`absolute_orientation`); annotations whose mapped
  position is within ``inlier_px`` (10 map pixels) of one of their candidates are inliers; a
  hypothesis needs more than 50 % inliers and (paper) the lowest normalised error (error /
  inliers) wins; it is refined on all its inliers. The winning rotation places every
  annotation (:func:`place_annotations`): at a candidate within ``placement_px`` of where the
  rotation puts it (matched) or, with none, at that position (inferred).
* Extensions of ours, because the two standing points differ by up to 2 m (sec. 6.1): anchors
  30-40 m away then move by up to 2-3 deg (12-17 px) of parallax that no rotation absorbs,
  while the doors and windows of the facades repeat every 15-20 px. Each is switchable:

  - placement gate and score: ``placement_px`` (25 px) is looser than the inlier gate, and
    the candidate placed is the one with the best NCC minus ``placement_penalty`` (0.2) x
    distance / ``placement_px`` (a look-alike one repetition further off needs an NCC ~0.12
    higher); ``placement_px = inlier_px``, ``placement_penalty = 0`` switch them off;
  - ``consensus_score``: among the valid hypotheses, the one with the highest placement score
    (the sum of those penalised NCCs, :meth:`_CandidateArrays.placement_score`) wins instead
    of the lowest normalised error, which prefers a rotation that lines up look-alikes one
    repetition away with near anchors' parallax over the true one; the winner is refined by
    least squares on all its placed matches (``refine_iterations``) while its score grows;
  - ``guided_search``: an inferred annotation is searched once more with NCC in a
    +-``placement_px`` window around its aligned position, which recovers true matches that
    were not among the three best candidates; with ``guided_all`` every matched annotation
    too, the window's best penalised NCC replacing its candidate when it scores better;
  - ``gravity_alignment`` (with the sensor prior): the accelerometers fix the tilt of both
    panoramas, so the alignment is the prior rotation turned about the vertical only (one
    degree of freedom, hypotheses from single matches and pairs), and a match must lie within
    ``gravity_v_px`` of the predicted elevation;
  - ``parallax_model``: the heading residuals of the matches are fitted with the parallax of a
    displaced standing point (:mod:`.parallax`; one trimmed refit, ``parallax_trim_sigmas``),
    each match judged against the fit of the others, and the annotations are placed again
    around the corrected positions, within a gate of ``parallax_gate_sigmas`` robust standard
    deviations of those leave-one-out residuals;
  - landmarks (:mod:`.landmarks`): distinctive patches of the source panorama stored with its
    annotations, matched and aligned like them but never placed for the user, so the rotation
    and the parallax are fitted on tens of matches instead of a handful.
* :class:`ReDetector` ties them together with the work queue of sec. 3.2 (finished tiles are
  queued and processed under a budget per frame) and the choice between several source
  panoramas near one GPS fix (sec. 6.1: the one whose annotations score best).

Map coordinates are those of :mod:`ar_tracking.core.panorama.cylinder` (u right, wrapping at
W; v down). A patch of side P with top-left pixel (x, y) has its centre at (x + (P-1)/2,
y + (P-1)/2).
"""
from __future__ import annotations

import itertools
import logging
import math
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import cv2
import numpy as np
import scipy.fft
from numpy.typing import NDArray

from ..rotations import align_about_axis, align_directions, rotations_about_axis, trace_angle
from ..panorama.cylinder import CylinderGeometry
from .parallax import ParallaxModel, fit_parallax

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MatchConfig:
    """Parameters of tile matching, the sensor prior and the alignment (units: map pixels)."""

    tile_size: int = 64
    #: Low-sequency Walsh coefficients compared by the pre-check (of 15 non-DC).
    walsh_coefficients: int = 10
    #: Smallest Walsh correlation for NCC to be computed at a position.
    walsh_min: float = 0.5
    #: Smallest NCC of a candidate.
    min_ncc: float = 0.55
    #: Candidates kept per annotation (sec. 4.3: three).
    candidates: int = 3
    #: Candidates of one annotation closer than this are one candidate.
    min_separation_px: float = 8.0
    #: Windows with a smaller grey-level standard deviation (8-bit units) are not matched.
    min_window_std: float = 2.0
    #: Sensor prior (sec. 4.2) on/off; half-width of the inner window (compass error), pixels.
    sensor_prior: bool = True
    prior_window_px: float = 57.0
    #: The outer window is this many times the inner one.
    prior_outer_factor: float = 3.0
    #: Score penalty at the edge of the outer window (linear in the distance from the inner).
    prior_penalty: float = 0.3
    #: Global alignment (sec. 4.3) on/off and its thresholds.
    ransac: bool = True
    inlier_px: float = 10.0
    #: Annotations are placed at a candidate within this distance of where the rotation puts
    #: them (parallax between the two standing points shifts them by up to ~17 pixels); with
    #: no candidate there, at the rotated position (inferred).
    placement_px: float = 25.0
    #: NCC penalty of a candidate at the edge of the placement gate (0.2: a look-alike one
    #: facade repetition, ~15 px, further from the aligned position needs an NCC ~0.12 higher).
    placement_penalty: float = 0.2
    #: Choose among the valid hypotheses by the placement score instead of the lowest normalised
    #: error (paper), and refine the winner on all its placed matches (extension of sec. 4.3).
    consensus_score: bool = True
    refine_iterations: int = 3
    min_inlier_ratio: float = 0.5
    min_inliers: int = 3
    max_hypotheses: int = 4000
    #: Guided re-detection of inferred annotations near their aligned position (an extension
    #: of sec. 4.3): on/off, smallest NCC, penalty at the edge of the +-placement_px window.
    guided_search: bool = True
    guided_min_ncc: float = 0.7
    guided_penalty: float = 0.2
    #: Guided re-match of the matched annotations too (after the alignment): a position in the
    #: window that scores better than their candidate replaces it.
    guided_all: bool = True
    #: With the sensor prior, a RANSAC hypothesis must lie within ``prior_window_px`` (the
    #: compass error) of the rotation the two absolute orientations give, and with no valid
    #: hypothesis that prior rotation aligns the panoramas (an extension joining sec. 4.2 and
    #: 4.3: a rotation the compass rules out is a coincidence of look-alikes).
    prior_alignment: bool = True
    #: With ``prior_alignment`` and the browsing panorama's up direction: the alignment is the
    #: prior rotation followed by a heading correction about the vertical (1 DoF). Gravity from
    #: the accelerometers fixes the tilt of both panoramas far better than the compass fixes
    #: the heading (averaged over a panorama the tilt error is a small fraction of a degree), so
    #: parallax and look-alikes can no longer tilt the rotation; a candidate whose elevation
    #: differs from the prior's by more than ``inlier_px`` makes no hypothesis.
    gravity_alignment: bool = True
    #: With ``gravity_alignment`` the rotation predicts the elevation to about a pixel (parallax
    #: moves anchors sideways): a candidate further above or below than this is not a match.
    gravity_v_px: float = 4.0
    #: After a gravity-constrained alignment with at least ``parallax_min_matches`` matches:
    #: fit the heading residuals with the parallax of a horizontal displacement (one common
    #: depth, :mod:`.parallax`) and place again around the corrected positions. Sigmas in rad:
    #: a match (with the depth differences), the prior on |t| / d.
    parallax_model: bool = True
    parallax_min_matches: int = 3
    parallax_sigma_match: float = 0.01
    parallax_sigma: float = 0.02
    #: One refit of the model without the matches beyond this many robust standard deviations
    #: of its residuals (landmarks far nearer than the anchors); 0: plain least squares.
    parallax_trim_sigmas: float = 3.0
    #: After the parallax model, matches must lie within this many robust standard deviations
    #: of the model's leave-one-out residuals of the matches (horizontal; between inlier_px and
    #: placement_px): fitted on tens of landmark matches the model predicts to a pixel or two,
    #: and a look-alike a facade repetition away no longer passes. 0: keep placement_px.
    parallax_gate_sigmas: float = 3.0
    #: An alignment is *supported* (its labels may be shown as placed) with at least this many
    #: matched annotations and landmarks, and, when both panoramas' orientations come with a
    #: heading covariance, with its rotation within ``support_prior_sigmas`` combined standard
    #: deviations (plus one inlier tolerance) of the prior rotation - or with at least
    #: ``strong_support_matches`` matches, which outvote a prior that is off. Unsupported
    #: placements are only approximate (see :attr:`Alignment.supported`).
    min_support_matches: int = 4
    support_prior_sigmas: float = 3.0
    strong_support_matches: int = 10
    #: An inferred placement (no match of its own) is supported only with at least
    #: ``local_support_matches`` matched annotations/landmarks within ``local_support_px`` columns
    #: of it: early on, with the matches all in the first finished tiles, the heading and the
    #: parallax fitted there are extrapolated to the far side of the panorama (1-3 deg off on the
    #: sample bag for the first seconds). The local tests apply to source panoramas with
    #: landmarks only (a handful of annotations alone is too sparse for them).
    local_support_matches: int = 2
    local_support_px: float = 171.0
    #: Matched labels too need ``local_support_matches`` other matches within ``local_support_px``
    #: (an isolated look-alike is then only approximate).
    local_support_matched: bool = True
    #: An inferred placement with fewer local matches is supported too when it is bracketed:
    #: a match on either side of it within ``bracket_support_px`` columns (0: off). Between
    #: matches the heading and the parallax are interpolated, not extrapolated as they are on the
    #: far side of the first finished tiles; late in a sweep a facade whose own anchor and
    #: supports do not match under the changed lighting lies between matched ones. 512 px = 90
    #: deg: the heading and the sinusoid of the parallax model are then pinned on both sides.
    bracket_support_px: float = 512.0
    #: Look-alike test of a matched annotation after the parallax model (0: off): when another
    #: local NCC maximum at least ``lookalike_sep_px`` from its match, inside the placement gate
    #: around its leave-one-out prediction, has an NCC within ``lookalike_margin`` of the
    #: match's, NCC cannot tell which is the anchor (a sign whose letters repeat, a facade
    #: repetition under changed lighting: the true position often matches worse). The
    #: annotation is then placed at the prediction, as inferred (fitted on the other matches,
    #: it is within a pixel or two where they surround it, and the local support rule decides
    #: whether it is shown). ``lookalike_sep_px`` ~ 1 deg: a runner-up closer than that does not
    #: make the label wrong.
    lookalike_margin: float = 0.1
    lookalike_sep_px: float = 6.0
    seed: int = 0


@dataclass(frozen=True)
class Candidate:
    """A match of one annotation: map position, penalised score and raw NCC."""

    u: float
    v: float
    score: float
    ncc: float


class CandidateList:
    """The best ``k`` candidates of one annotation, at least ``sep`` pixels apart."""

    def __init__(self, k: int, sep: float, width: int) -> None:
        self.k, self.sep, self.width = k, sep, width
        self.items: list[Candidate] = []

    def add(self, c: Candidate) -> bool:
        for i, o in enumerate(self.items):
            du = abs(o.u - c.u) % self.width
            if math.hypot(min(du, self.width - du), o.v - c.v) < self.sep:
                if c.score <= o.score:
                    return False
                self.items.pop(i)
                break
        self.items.append(c)
        self.items.sort(key=lambda x: -x.score)
        changed = c in self.items[:self.k]
        del self.items[self.k:]
        return changed

    @property
    def best(self) -> Candidate | None:
        return self.items[0] if self.items else None


#: 4-point Walsh functions in sequency order.
_H4 = np.array([[1, 1, 1, 1], [1, 1, -1, -1], [1, -1, -1, 1], [1, -1, 1, -1]], np.float32)


def _walsh_pairs(n_keep: int) -> list[tuple[int, int]]:
    """(row, column) sequencies of the ``n_keep`` lowest-sequency 2-D Walsh functions, DC excluded."""
    order = sorted(((i, j) for i in range(4) for j in range(4) if (i, j) != (0, 0)),
                   key=lambda ij: (ij[0] + ij[1], max(ij), ij[0]))
    return order[:n_keep]


def _walsh_basis(n_keep: int) -> NDArray[np.float32]:
    """(16, n_keep) projection of 4 x 4 block means onto the lowest-sequency 2-D Walsh
    functions, DC excluded (unnormalised: the vectors are normalised afterwards)."""
    return np.stack([np.outer(_H4[i], _H4[j]).ravel() for i, j in _walsh_pairs(n_keep)], 1)


def _unit_rows(x: NDArray[np.float32]) -> tuple[NDArray[np.float32], NDArray[np.bool_]]:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    ok = n[..., 0] > 1e-6
    return np.asarray(x / np.where(n > 1e-6, n, 1.0), dtype=np.float32), ok


def patch_walsh(patches: NDArray[np.float32], basis: NDArray[np.float32]) -> NDArray[np.float32]:
    """Normalised Walsh vectors (n, k) of patches (n, P, P)."""
    n, P, _ = patches.shape
    b = P // 4
    means = patches.reshape(n, 4, b, 4, b).mean(axis=(2, 4)).reshape(n, 16)
    return _unit_rows(means @ basis)[0]


class TileMatcher:
    """Walsh pre-check + NCC of a set of equal-size patches against map tiles (sec. 3.2)."""

    def __init__(self, patches: Sequence[NDArray[np.uint8]], config: MatchConfig | None = None,
                 geometry: CylinderGeometry | None = None) -> None:
        self.config = cfg = config or MatchConfig()
        self.geometry = geometry or CylinderGeometry()
        arr = np.asarray(patches, np.float32)
        if arr.ndim != 3 or arr.shape[1] != arr.shape[2] or arr.shape[1] % 4:
            raise ValueError(f'patches must be (n, P, P) with P a multiple of 4, got {arr.shape}')
        self.patches = arr
        self.P = arr.shape[1]
        self.basis = _walsh_basis(cfg.walsh_coefficients)
        self.pairs = _walsh_pairs(cfg.walsh_coefficients)
        self.basis_t = np.ascontiguousarray(self.basis.T)
        self.walsh = patch_walsh(arr, self.basis)
        flat = arr.reshape(len(arr), -1) - arr.reshape(len(arr), -1).mean(axis=1, keepdims=True)
        unit = (flat / np.maximum(np.linalg.norm(flat, axis=1, keepdims=True), 1e-6)).astype(np.float32)
        self.n_fft = cfg.tile_size + self.P
        flipped = unit.reshape(arr.shape)[:, ::-1, ::-1]
        self.patch_fft = scipy.fft.rfft2(flipped, s=(self.n_fft, self.n_fft))
        self.ncc_ops = 0
        self.walsh_rejected = 0

    def region(self, gray: NDArray[np.float32], mapped: NDArray[np.bool_] | None, tile: int
               ) -> tuple[NDArray[np.float32], NDArray[np.float32], int, int]:
        """(region, mapped fraction, x0, y0): the map pixels all patch positions with their
        top-left in the tile need; columns wrap, rows outside the map are unmapped."""
        T, P, h = self.config.tile_size, self.P, self.P // 2
        H, W = gray.shape
        cols_n = W // T
        tr, tc = divmod(tile, cols_n)
        x0, y0 = tc * T - h, tr * T - h
        n = T + P - 1
        if 0 <= x0 and x0 + n <= W and 0 <= y0 and y0 + n <= H:  # no wrap, inside: views
            reg = np.ascontiguousarray(gray[y0:y0 + n, x0:x0 + n], dtype=np.float32)
            if mapped is None:
                return reg, np.ones((n, n), np.float32), x0, y0
            m = mapped[y0:y0 + n, x0:x0 + n].astype(np.float32)
            return np.where(m > 0, reg, np.float32(0.0)), m, x0, y0
        cols = np.arange(x0, x0 + n) % W
        rows = np.arange(y0, y0 + n)
        inside = (rows >= 0) & (rows < H)
        rows_c = np.clip(rows, 0, H - 1)
        reg = gray[np.ix_(rows_c, cols)].astype(np.float32, copy=False)
        if mapped is None:
            m = np.ones((n, n), np.float32)
        else:
            m = mapped[np.ix_(rows_c, cols)].astype(np.float32)
        m[~inside] = 0.0
        reg = np.where(m > 0, reg, 0.0).astype(np.float32)
        return reg, m, x0, y0

    def match_tile(self, gray: NDArray[np.float32], mapped: NDArray[np.bool_] | None, tile: int,
                   active: Sequence[int] | None = None, expected_uv: Array | None = None
                   ) -> dict[int, list[Candidate]]:
        """Candidates (up to ``candidates`` per annotation) whose patch top-left lies in
        ``tile``, for the annotations ``active`` (default all). ``expected_uv`` (n, 2): the
        sensor prior's expected positions (NaN rows: no prior for that annotation)."""
        cfg, P, T = self.config, self.P, self.config.tile_size
        idx = list(range(len(self.patches))) if active is None else list(active)
        out: dict[int, list[Candidate]] = {}
        if not idx:
            return out
        reg, m, x0, y0 = self.region(gray, mapped, tile)
        c = (P - 1) / 2.0
        # Prior: which annotations can appear in this tile at all (outer window).
        us = x0 + c + np.arange(T)
        vs = y0 + c + np.arange(T)
        penalty = {}
        if cfg.sensor_prior and expected_uv is not None:
            inner = cfg.prior_window_px
            outer = inner * cfg.prior_outer_factor
            keep = []
            for i in idx:
                eu, ev = expected_uv[i]
                if not (np.isfinite(eu) and np.isfinite(ev)):
                    keep.append(i)
                    continue
                du = self.geometry.column_distance(us, eu)
                dv = np.abs(vs - ev)
                if du.min() > outer or dv.min() > outer:
                    continue
                dist = np.maximum(np.maximum(du[None, :], dv[:, None]) - inner, 0.0)
                pen = cfg.prior_penalty * dist / max(outer - inner, 1e-9)
                pen[np.maximum(du[None, :], dv[:, None]) > outer] = np.inf
                penalty[i] = pen
                keep.append(i)
            idx = keep
            if not idx:
                return out
        # Valid windows: fully mapped and textured.
        box = (P, P)
        frac = cv2.boxFilter(m, -1, box, anchor=(0, 0), normalize=True, borderType=cv2.BORDER_CONSTANT)[:T, :T]
        mean = cv2.boxFilter(reg, -1, box, anchor=(0, 0), normalize=True, borderType=cv2.BORDER_CONSTANT)[:T, :T]
        sq = cv2.boxFilter(reg * reg, -1, box, anchor=(0, 0), normalize=True, borderType=cv2.BORDER_CONSTANT)[:T, :T]
        valid = (frac > 0.999) & (sq - mean * mean > cfg.min_window_std ** 2)
        if not valid.any():
            return out
        # Walsh pre-check for all positions and annotations at once.
        b = P // 4
        bm = cv2.boxFilter(reg, -1, (b, b), anchor=(0, 0), normalize=True, borderType=cv2.BORDER_CONSTANT)
        # Walsh coefficients of the 4 x 4 block means at every position: the 16 shifted
        # block-mean images (16, T*T) times the basis, one matrix product; annotation-major.
        feats = np.empty((16, T, T), np.float32)
        for q in range(16):
            i, j = divmod(q, 4)
            feats[q] = bm[i * b:i * b + T, j * b:j * b + T]
        coef = self.basis_t @ feats.reshape(16, T * T)  # (k, T*T)
        norm = np.sqrt(np.einsum('kp,kp->p', coef, coef))
        ok = (norm > 1e-6) & valid.reshape(-1)
        wscore = (self.walsh[idx] @ coef) / np.where(norm > 1e-6, norm, 1.0)  # (n, T*T)
        passed = (wscore >= cfg.walsh_min) & ok[None, :]
        alive = np.flatnonzero(passed.any(axis=1))
        self.walsh_rejected += len(idx) - alive.size
        if alive.size == 0:
            return out
        # NCC of the survivors: one batched FFT correlation with the zero-mean, unit-norm
        # patches; the window norms (shared by all annotations) from the box filters.
        sel = [idx[k] for k in alive]
        n_fft = self.n_fft
        corr = scipy.fft.irfft2(scipy.fft.rfft2(reg, s=(n_fft, n_fft))[None] * self.patch_fft[sel],
                                s=(n_fft, n_fft), workers=1)[:, P - 1:P - 1 + T, P - 1:P - 1 + T]
        wnorm = np.sqrt(np.maximum(sq - mean * mean, 1e-12) * (P * P))
        ncc = np.where(passed[alive].reshape(-1, T, T), corr / wnorm[None], -1.0).astype(np.float32)
        self.ncc_ops += alive.size
        best = ncc.reshape(len(sel), -1).max(axis=1)
        for k in np.flatnonzero(best >= cfg.min_ncc):
            i = sel[k]
            res = ncc[k]
            score = res - penalty[i].astype(np.float32) if i in penalty else res.copy()
            cands = self._peaks(res, score, x0, y0)
            if cands:
                out[i] = cands
        return out

    def _peaks(self, res: NDArray[np.float32], s: NDArray[np.float32], x0: int, y0: int) -> list[Candidate]:
        """Up to ``candidates`` local maxima of the (penalised) score ``s`` (modified in place),
        at least ``min_separation_px`` apart, refined to sub-pixel on the NCC surface."""
        cfg = self.config
        W = self.geometry.width
        c = (self.P - 1) / 2.0
        s[res < cfg.min_ncc] = -np.inf
        out: list[Candidate] = []
        r = int(math.ceil(cfg.min_separation_px))
        T = res.shape[0]
        for _ in range(cfg.candidates):
            _, top, _, (x, y) = cv2.minMaxLoc(s)
            if not np.isfinite(top) or top < -1.5:
                break
            dx = dy = 0.0
            if 0 < x < T - 1 and res[y, x - 1] > -1 and res[y, x + 1] > -1:
                den = float(res[y, x - 1] - 2 * res[y, x] + res[y, x + 1])
                dx = min(0.5, max(-0.5, 0.5 * float(res[y, x - 1] - res[y, x + 1]) / den)) if den < 0 else 0.0
            if 0 < y < T - 1 and res[y - 1, x] > -1 and res[y + 1, x] > -1:
                den = float(res[y - 1, x] - 2 * res[y, x] + res[y + 1, x])
                dy = min(0.5, max(-0.5, 0.5 * float(res[y - 1, x] - res[y + 1, x]) / den)) if den < 0 else 0.0
            out.append(Candidate(u=float((x0 + x + dx + c) % W), v=float(y0 + y + dy + c),
                                 score=float(top), ncc=float(res[y, x])))
            s[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1] = -np.inf
        return out

# -- global alignment (sec. 4.3) ------------------------------------------------------------

def absolute_orientation(a: Array, b: Array, weights: Array | None = None) -> Array:
    """The rotation R minimising sum w |R a_i - b_i|^2 for unit vectors (n >= 2, 3)
    (the absolute orientation of two sets of directions, Horn 1987; core.rotations)."""
    return align_directions(a, b, weights)


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


def ransac_alignment(source_dirs: Array, candidates: Sequence[Sequence[Candidate]],
                     config: MatchConfig | None = None, geometry: CylinderGeometry | None = None,
                     rng: np.random.Generator | None = None, R_prior: Array | None = None,
                     up: Array | None = None) -> Alignment:
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
    matches and pairs (:func:`_heading_hypotheses`) and refinements fit the heading alone."""
    cfg = config or MatchConfig()
    geo = geometry or CylinderGeometry()
    src = np.asarray(source_dirs, float).reshape(-1, 3)
    n = len(src)
    with_c = [i for i in range(n) if candidates[i]]
    # Candidate directions and positions, per annotation.
    cu = [np.array([c.u for c in candidates[i]]) for i in range(n)]
    cv_ = [np.array([c.v for c in candidates[i]]) for i in range(n)]
    cd = [geo.unproject(cu[i], cv_[i]) if len(cu[i]) else np.zeros((0, 3)) for i in range(n)]
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
        return _prior_alignment(R_prior, src, candidates, cs, cd, cfg, geo, fit, v_tol)

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
    dist = np.nanmin(dd, axis=2)  # (H, n)
    inl = dist < cfg.inlier_px
    n_inl = inl.sum(axis=1)
    valid = n_inl >= need
    if not valid.any():
        return fallback()
    nerr = np.where(valid, np.where(inl, dist, 0.0).sum(axis=1) / np.maximum(n_inl, 1), np.inf)
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
    best = (float(nerr[h]), Rs[h], [with_c[r] for r in np.flatnonzero(inl[h])])
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
    result.placements = place_annotations(R, src, candidates, cfg, geo, v_tol)
    result.v_tol = v_tol
    return result


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
                     v_tol: float | None = None) -> Alignment:
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
    placements = place_annotations(R, src, candidates, cfg, geo, v_tol)
    return Alignment(R, placements, [p.index for p in placements if p.status == 'matched'], v_tol=v_tol)


def place_annotations(R: Array, source_dirs: Array, candidates: Sequence[Sequence[Candidate]],
                      config: MatchConfig | None = None, geometry: CylinderGeometry | None = None,
                      v_tol: float | None = None, predicted: Array | None = None) -> list[Placement]:
    """Every annotation placed by the rotation R (sec. 4.3): at its candidate within
    ``placement_px`` of where R puts it with the best NCC minus ``placement_penalty`` x
    distance / ``placement_px`` (matched; the NCC, not the prior-penalised score: the rotation
    supersedes the compass), or, with none there, at that position (inferred). ``v_tol``: a
    candidate further above or below than this is none (``gravity_v_px``). ``predicted`` (n, 3):
    the directions to use instead of R's (the rotation with the parallax model)."""
    cfg = config or MatchConfig()
    geo = geometry or CylinderGeometry()
    src = np.asarray(source_dirs, float).reshape(-1, 3)
    pred = src @ np.asarray(R, float).T if predicted is None else np.asarray(predicted, float)
    with_c = [i for i in range(len(src)) if candidates[i]]
    best: dict[int, int] = {}
    if with_c:
        cs = _CandidateArrays(candidates, with_c, v_tol)
        value = cs.values(cs.distances_from(pred[with_c][None], geo)[0], cfg)
        best = {i: int(np.argmax(value[r])) for r, i in enumerate(with_c) if np.isfinite(value[r]).any()}
    out = []
    for i in range(len(src)):
        if i in best:
            c = candidates[i][best[i]]
            out.append(Placement(i, c.u, c.v, geo.unproject(np.array(c.u), np.array(c.v)), 'matched', c.ncc))
        else:
            pu, pv = geo.project(pred[i])
            out.append(Placement(i, float(pu), float(pv), pred[i], 'inferred', float('nan')))
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


# -- the scheduler: queue, budget, several source panoramas ----------------------------------

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
        patch = None
        for matcher, ids in self.matchers:
            if index in ids:
                patch = matcher.patches[ids.index(index)]
        if patch is None:
            return None
        P = patch.shape[0]
        r = int(math.ceil(radius_px))
        rv = r if v_tol is None else int(math.ceil(min(v_tol, radius_px)))
        x0 = int(round(cu - (P - 1) / 2)) - r
        y0 = int(round(cv_ - (P - 1) / 2)) - rv
        if y0 < 0 or y0 + P + 2 * rv > gray.shape[0]:
            return None
        cols = np.arange(x0, x0 + P + 2 * r) % self.geometry.width
        reg = gray[y0:y0 + P + 2 * rv][:, cols].astype(np.float32)
        if mapped is not None:
            m = mapped[y0:y0 + P + 2 * rv][:, cols].astype(np.float32)
            full = cv2.boxFilter(m, -1, (P, P), anchor=(0, 0), normalize=True,
                                 borderType=cv2.BORDER_CONSTANT)[:2 * rv + 1, :2 * r + 1]
        else:
            full = np.ones((2 * rv + 1, 2 * r + 1), np.float32)
        res: NDArray[np.float32] = np.asarray(
            cv2.matchTemplate(reg, patch.astype(np.float32), cv2.TM_CCOEFF_NORMED), np.float32)
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
