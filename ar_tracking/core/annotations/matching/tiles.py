"""Tile matching (Langlotz 2011 sec. 3.2, 4.2): the Walsh-transform pre-check and the NCC of
the annotations' patches against one finished map tile at a time, with the sensor prior's
search windows; the best candidates per annotation (:class:`CandidateList`)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np
import scipy.fft
from numpy.typing import NDArray

from ...panorama.cylinder import CylinderGeometry
from .config import MatchConfig

Array = NDArray[np.float64]


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
