"""Landmarks: distinctive patches of a source panorama that help align it (extends sec. 4.3).

The global alignment of sec. 4.3 rests on the annotations alone, 4-6 per spot. Under changed
lighting one or two of them often do not match, and then the rotation (and the parallax model
of :mod:`.parallax`) comes from one or two matches: a browsing spot a metre from the authoring
spot turns anchors 40-70 m away by up to ~1.5 deg, differently for each azimuth, so the
annotations placed from so few matches (inferred) land more than a degree off. The source
panorama has far more texture than its annotations. When an annotated spot is authored, a few
dozen small patches of it are stored as well (about 300 bytes each, never shown): the
re-detector matches them exactly like annotations, and they take part in the alignment, the
parallax fit and the placement gate, so the rotation and the parallax are fitted on tens of
matches around the whole circle instead of a handful.

A good landmark is:

* a corner (Shi-Tomasi, ``cv2.goodFeaturesToTrack``): it fixes both map coordinates;
* unique in its neighbourhood: facades repeat windows every ~15 px, and a patch whose NCC with
  a position within ``search_px`` of it exceeds ``max_self_similarity`` would match a
  look-alike; the least self-similar corners are taken first;
* above the horizon by ``min_elevation_deg`` when the panorama's orientation is known: things
  above eye level (facades, roofs, trees) are far, the ground and street furniture below it are
  near, and a near landmark's parallax (tens of degrees at 2-3 m) says nothing about the far
  anchors' one;
* spread around the panorama: no two closer than ``min_separation_px``.

Besides these, each annotation gets up to ``support_count`` **support landmarks**: unique
corners in a window of +-``support_u_px`` x +-``support_v_px`` around its anchor (not on the
anchor itself), at least ``support_separation_px`` apart, at any elevation. The parallax model
is a sinusoid in azimuth fitted on the matches; where none of the other landmarks matched near
an anchor (a shadowed facade), its value there is an extrapolation, and an anchor 70 m away
was predicted 15 px (2.7 deg) off by a fit bent by landmarks 35 m away on the other side.
Landmarks next to every anchor, mostly on its facade and at its depth, pin the fit where the
annotations are.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from ..panorama.cylinder import CylinderGeometry
from .patches import cut_patch


@dataclass(frozen=True)
class LandmarkConfig:
    """How many landmarks an authored spot stores and what makes one (units: map pixels)."""

    count: int = 24
    patch_px: int = 16
    #: Shi-Tomasi corners considered (the strongest; quality relative to the best one).
    max_corners: int = 600
    corner_quality: float = 0.01
    #: A landmark is unique if no position within +-search_px (+-search_v_px vertically),
    #: other than itself (+-4 px), matches its patch with an NCC above max_self_similarity.
    search_px: int = 48
    search_v_px: int = 12
    max_self_similarity: float = 0.8
    #: Landmarks below this elevation are not taken (with a known orientation only).
    min_elevation_deg: float = 2.0
    #: Smallest map distance between two landmarks; 0: half the mean spacing of ``count``
    #: landmarks around the circle.
    min_separation_px: float = 0.0
    #: Support landmarks per annotation (``avoid``): within +-support_u_px x +-support_v_px of
    #: the anchor, not within support_exclude_px of it, support_separation_px apart.
    support_count: int = 4
    support_u_px: float = 40.0
    support_v_px: float = 20.0
    support_exclude_px: float = 6.0
    support_separation_px: float = 8.0


@dataclass(frozen=True)
class LandmarkPatch:
    """A selected landmark: map position, patch and unit direction in the panorama frame."""

    u: float
    v: float
    patch: NDArray[np.uint8]
    direction: NDArray[np.float64]
    self_similarity: float


def self_similarity(gray: NDArray, mapped: NDArray[np.bool_], u: float, v: float,
                    patch: NDArray[np.uint8], config: LandmarkConfig) -> float:
    """Best NCC of ``patch`` at a position of its neighbourhood other than its own (+-4 px);
    1.0 when the neighbourhood is not fully mapped (it cannot be judged)."""
    H, W = gray.shape
    P = patch.shape[0]
    x0 = int(round(u - (P - 1) / 2.0))
    y0 = int(round(v - (P - 1) / 2.0))
    r, rv = config.search_px, config.search_v_px
    ys, ye = max(0, y0 - rv), min(H, y0 + P + rv)
    cols = np.arange(x0 - r, x0 + P + r) % W
    if not mapped[ys:ye][:, cols].all():
        return 1.0
    region = np.asarray(gray, np.float32)[ys:ye][:, cols]
    ncc = cv2.matchTemplate(region, patch.astype(np.float32), cv2.TM_CCOEFF_NORMED)
    cy, cx = y0 - ys, r
    ncc[max(0, cy - 4):cy + 5, max(0, cx - 4):cx + 5] = -1.0
    ncc[~np.isfinite(ncc)] = -1.0
    return float(ncc.max())


def select_landmarks(gray: NDArray, mapped: NDArray[np.bool_], geometry: CylinderGeometry,
                     up: NDArray[np.float64] | None = None,
                     config: LandmarkConfig | None = None,
                     avoid: NDArray[np.float64] | None = None) -> list[LandmarkPatch]:
    """Up to ``config.count`` landmarks of a finished map (module docstring for the rules).

    ``gray`` (H, W) grey map (8-bit units), ``mapped`` its mask; ``up`` the world's up direction
    in the panorama frame (row 2 of R_enu_panorama), None if unknown (no elevation rule);
    ``avoid`` (n, 3) directions of the annotations: no landmark within the separation of one
    (it would count the same support area twice), and after the ``count`` landmarks the
    support landmarks of each (:func:`select_support_landmarks`)."""
    cfg = config or LandmarkConfig()
    if cfg.count <= 0:
        return []
    P = cfg.patch_px
    margin = _inner_mask(mapped, P)
    accept = None
    if up is not None:
        sin_min = math.sin(math.radians(cfg.min_elevation_deg))
        accept = lambda d: float(d @ up) >= sin_min  # noqa: E731
    found = _unique_corners(gray, mapped, geometry, margin, cfg, cfg.max_corners, P * 0.75, accept)
    found.sort(key=lambda lm: lm.self_similarity)
    sep = cfg.min_separation_px or geometry.width / (2.0 * cfg.count)
    taken_u: list[float] = []
    taken_v: list[float] = []
    if avoid is not None and len(avoid):
        au, av = geometry.project(np.asarray(avoid, float).reshape(-1, 3))
        taken_u, taken_v = list(np.atleast_1d(au)), list(np.atleast_1d(av))
    chosen: list[LandmarkPatch] = []
    for lm in found:
        if taken_u and np.min(geometry.map_distance(np.asarray(taken_u), np.asarray(taken_v), lm.u, lm.v)) < sep:
            continue
        chosen.append(lm)
        taken_u.append(lm.u)
        taken_v.append(lm.v)
        if len(chosen) >= cfg.count:
            break
    if avoid is not None and len(avoid):
        chosen += select_support_landmarks(gray, mapped, geometry, avoid, cfg, chosen)
    return chosen


def select_support_landmarks(gray: NDArray, mapped: NDArray[np.bool_], geometry: CylinderGeometry,
                             anchors: NDArray[np.float64], config: LandmarkConfig | None = None,
                             taken: list[LandmarkPatch] | None = None) -> list[LandmarkPatch]:
    """Up to ``config.support_count`` support landmarks around each anchor (``anchors``: (n, 3)
    directions in the panorama frame; module docstring), none within ``support_separation_px``
    of another or of a landmark in ``taken``."""
    cfg = config or LandmarkConfig()
    if cfg.support_count <= 0:
        return []
    geo = geometry
    margin = _inner_mask(mapped, cfg.patch_px)
    au, av = geo.project(np.asarray(anchors, float).reshape(-1, 3))
    chosen: list[LandmarkPatch] = []
    near = list(taken or [])
    for ua, va in zip(np.atleast_1d(au), np.atleast_1d(av)):
        window = np.zeros_like(margin)
        cols = np.arange(int(ua - cfg.support_u_px), int(ua + cfg.support_u_px) + 1) % geo.width
        y0, y1 = max(0, int(va - cfg.support_v_px)), int(va + cfg.support_v_px) + 1
        window[y0:y1, cols] = 1
        window &= margin
        found = [lm for lm in _unique_corners(gray, mapped, geo, window, cfg, 60, cfg.support_exclude_px)
                 if geo.map_distance(np.array(lm.u), np.array(lm.v), ua, va) >= cfg.support_exclude_px]
        found.sort(key=lambda lm: lm.self_similarity)
        mine = 0
        for lm in found:
            if near and np.min(geo.map_distance(np.array([t.u for t in near]), np.array([t.v for t in near]),
                                                lm.u, lm.v)) < cfg.support_separation_px:
                continue
            chosen.append(lm)
            near.append(lm)
            mine += 1
            if mine >= cfg.support_count:
                break
    return chosen


def _inner_mask(mapped: NDArray[np.bool_], patch_px: int) -> NDArray[np.uint8]:
    """Where a patch (with the self-similarity margin) lies inside the mapped area."""
    return np.asarray(cv2.erode(np.asarray(mapped, np.uint8), np.ones((patch_px + 9, patch_px + 9), np.uint8)), dtype=np.uint8)


def _unique_corners(gray: NDArray, mapped: NDArray[np.bool_], geometry: CylinderGeometry,
                    mask: NDArray[np.uint8], cfg: LandmarkConfig, max_corners: int,
                    min_distance: float,
                    accept: Callable[[NDArray[np.float64]], bool] | None = None) -> list[LandmarkPatch]:
    """Shi-Tomasi corners inside ``mask`` whose patch is unique in its neighbourhood
    (self-similarity at most ``cfg.max_self_similarity``) and, with ``accept``, whose direction
    it accepts."""
    pts = cv2.goodFeaturesToTrack(np.asarray(gray, np.float32), maxCorners=max_corners,
                                  qualityLevel=cfg.corner_quality, minDistance=min_distance, mask=mask)
    if pts is None:
        return []
    found: list[LandmarkPatch] = []
    for u, v in pts.reshape(-1, 2).astype(float):
        patch, d, _ = cut_patch(gray, mapped, u, v, cfg.patch_px, geometry)
        if patch is None or d is None or (accept is not None and not accept(d)):
            continue
        s = self_similarity(gray, mapped, u, v, patch, cfg)
        if s <= cfg.max_self_similarity:
            found.append(LandmarkPatch(u, v, patch, d, s))
    return found
