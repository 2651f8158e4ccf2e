"""Image pyramid and multi-scale Shi-Tomasi corners (Klein & Murray 2009, sec. 3.1).

The phone version of PTAM keeps far fewer map points than PTAM on the PC and requires each new
feature to be a good Shi-Tomasi (ST) corner in *all* of L0, L1 and L2. That makes the detector
cheap: the exhaustive ST search with non-maximum suppression runs only on the small L2 image;
every L2 maximum is projected to L1 and moved there by iterative ascent of the ST score (the best
pixel of a 3x3 window becomes the next centre, at most three steps); if the L1 corner is good the
same is repeated on L0, whose position is the corner's position. Because the corner is a corner
at three scales, the tracker can later fix its search level and vary the template's source level
(sec. 4) and still have a trackable template.

``small_blurry_image`` is the coarsest pyramid level, Gaussian-blurred and made zero-mean: the
full-frame rotation prior (sec. 4) aligns these images and the keyframe relocaliser (ECCV'08)
compares them.
"""
from __future__ import annotations

import logging
from typing import Literal, overload

import cv2
import numpy as np
from numpy.typing import NDArray

from .camera import PYRAMID_LEVELS

log = logging.getLogger(__name__)

Array = NDArray[np.float64]
Image = NDArray[np.uint8]

#: Default minimum ST score (smallest eigenvalue of the 3x3 structure tensor from 3x3 Sobel
#: gradients, as returned by ``cv2.cornerMinEigenVal`` on a uint8 image, i.e. intensities scaled
#: to [0, 1]). A clean step edge of contrast 1 scores ~0; textured print ~1e-3..1e-2.
DEFAULT_MIN_SCORE = 2.0e-4
#: Levels on which a new feature must be a good corner (sec. 3.1: all of L0, L1, L2).
CORNER_LEVELS = 3
#: Iterative-ascent steps per level (sec. 3.1: "until ... three iterations are exceeded").
ASCENT_ITERATIONS = 3


def build_pyramid(gray: Image, levels: int = PYRAMID_LEVELS) -> list[Image]:
    """The image pyramid L0..L(levels-1), each level half the previous (``cv2.pyrDown``).

    Five levels as in sec. 3.1 (320x240 -> 20x15; 640x480 -> 40x30).
    """
    img = np.ascontiguousarray(gray, dtype=np.uint8)
    pyr = [img]
    for _ in range(1, levels):
        # OpenCV's stubs type every result as MatLike; pyrDown keeps uint8 (no copy here).
        pyr.append(np.asarray(cv2.pyrDown(pyr[-1]), dtype=np.uint8))
    return pyr


def shi_tomasi_score(img: Image) -> NDArray[np.float32]:
    """Per-pixel Shi-Tomasi score (minimum eigenvalue of the structure tensor), float32."""
    return np.asarray(cv2.cornerMinEigenVal(img, blockSize=3, ksize=3), dtype=np.float32)  # CV_32F: no copy


def _ascend(score: NDArray[np.float32], xy: NDArray[np.int64], border: int,
            iterations: int = ASCENT_ITERATIONS) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """Iterative 3x3 ascent of ``score`` from integer positions ``xy`` (N, 2) (vectorised).

    Each step moves every point to the best pixel of its 3x3 neighbourhood; points stay inside
    ``border`` (at least 1). Returns the final positions and their scores.
    """
    h, w = score.shape
    b = max(1, border)
    xy = xy.copy()
    xy[:, 0] = np.clip(xy[:, 0], b, w - 1 - b)
    xy[:, 1] = np.clip(xy[:, 1], b, h - 1 - b)
    dx = np.array([-1, 0, 1, -1, 0, 1, -1, 0, 1])
    dy = np.array([-1, -1, -1, 0, 0, 0, 1, 1, 1])
    for _ in range(iterations):
        nx = xy[:, 0:1] + dx[None, :]
        ny = xy[:, 1:2] + dy[None, :]
        s = score[ny, nx]
        best = np.argmax(s, axis=1)
        moved = best != 4
        if not np.any(moved):
            break
        xy[:, 0] = np.clip(nx[np.arange(len(xy)), best], b, w - 1 - b)
        xy[:, 1] = np.clip(ny[np.arange(len(xy)), best], b, h - 1 - b)
    return xy, score[xy[:, 1], xy[:, 0]]


Corners = tuple[Array, NDArray[np.int64]]
CornersWithScores = tuple[Array, NDArray[np.int64], Array]


@overload
def multiscale_corners(pyramid: list[Image], max_corners: int = ..., min_score: float = ...,
                       border: int = ..., exclude_uv: Array | None = ..., exclude_radius_px: float = ...,
                       return_scores: Literal[False] = ...) -> Corners: ...


@overload
def multiscale_corners(pyramid: list[Image], max_corners: int = ..., min_score: float = ...,
                       border: int = ..., exclude_uv: Array | None = ..., exclude_radius_px: float = ...,
                       *, return_scores: Literal[True]) -> CornersWithScores: ...


def multiscale_corners(pyramid: list[Image], max_corners: int = 200,
                       min_score: float = DEFAULT_MIN_SCORE, border: int = 8,
                       exclude_uv: Array | None = None, exclude_radius_px: float = 10.0,
                       return_scores: bool = False) -> Corners | CornersWithScores:
    """Corners that are good ST corners in L0, L1 and L2 (sec. 3.1), strongest first.

    Exhaustive ST maxima (3x3 non-maximum suppression, score >= ``min_score``) on L2 are projected
    to L1 and refined by iterative 3x3 ascent (<= 3 steps), kept if the L1 score is good, then the
    same on L0. ``border`` is in level-0 pixels (the L0 position must be at least that far from
    the image edge). Corners within ``exclude_radius_px`` (level 0) of ``exclude_uv`` (existing
    features) or of a stronger accepted corner are dropped.

    Returns ``(uv0 (N, 2) float level-0 positions, levels (N,) int)`` sorted by decreasing L0
    score; ``levels`` is the level the position was localised on (always 0 here, kept so callers
    can use it as the measurement level). With ``return_scores`` a third array, the L0 ST scores.
    """
    empty2: Corners = (np.zeros((0, 2)), np.zeros(0, dtype=np.int64))
    empty: Corners | CornersWithScores = empty2 + (np.zeros(0),) if return_scores else empty2
    if len(pyramid) < CORNER_LEVELS:
        return empty
    l2 = pyramid[2]
    s2 = shi_tomasi_score(l2)
    b2 = max(2, int(np.ceil(border / 4.0)))
    h2, w2 = s2.shape
    if h2 <= 2 * b2 + 2 or w2 <= 2 * b2 + 2:
        return empty
    dil = cv2.dilate(s2, np.ones((3, 3), np.uint8))
    mask = (s2 >= dil) & (s2 >= min_score)
    mask[:b2, :] = False
    mask[-b2:, :] = False
    mask[:, :b2] = False
    mask[:, -b2:] = False
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return empty
    # Keep the strongest L2 maxima (generous: later levels and exclusion reject some).
    order = np.argsort(-s2[ys, xs])[: max(4 * max_corners, 64)]
    xy = np.column_stack([xs[order], ys[order]]).astype(np.int64)

    for level in (1, 0):
        # Project (level+1) integer pixel centres to this level: u_l = 2 u_{l+1} + 0.5.
        xy = np.rint(2 * xy + 0.5).astype(np.int64)
        score = shi_tomasi_score(pyramid[level])
        b = max(1, int(np.ceil(border / (2 ** level))))
        xy, sc = _ascend(score, xy, b)
        good = sc >= min_score
        xy, sc = xy[good], sc[good]
        if len(xy) == 0:
            return empty

    # Several L2 maxima may ascend to the same L0 corner: de-duplicate and suppress neighbours.
    order = np.argsort(-sc, kind='stable')
    xy, sc = xy[order], sc[order]
    uv = xy.astype(float)
    keep: list[int] = []
    r2 = float(exclude_radius_px) ** 2
    excl = None if exclude_uv is None else np.asarray(exclude_uv, float).reshape(-1, 2)
    if excl is not None and len(excl):
        d2 = ((uv[:, None, :] - excl[None, :, :]) ** 2).sum(-1).min(1)
        free = d2 > r2
    else:
        free = np.ones(len(uv), bool)
    sep2 = max(r2, 4.0)
    for i in range(len(uv)):
        if not free[i]:
            continue
        if keep:
            d2k = ((uv[keep] - uv[i]) ** 2).sum(1)
            if np.any(d2k < sep2):
                continue
        keep.append(i)
        if len(keep) >= max_corners:
            break
    idx = np.array(keep, dtype=np.int64)
    out: Corners = (uv[idx].reshape(-1, 2), np.zeros(len(idx), dtype=np.int64))
    if return_scores:
        return out + (sc[idx].astype(float),)
    return out


def small_blurry_image(pyramid: list[Image], sigma: float = 0.75) -> NDArray[np.float32]:
    """Coarsest level, Gaussian-blurred and zero-mean (float32): the 'small blurry image'.

    Used by the full-frame rotation prior (sec. 4) and the keyframe relocaliser (ECCV'08).
    """
    img = pyramid[-1].astype(np.float32)
    if sigma > 0:
        img = np.asarray(cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE),
                         dtype=np.float32)  # float32 in, float32 out: no copy
    return (img - float(img.mean())).astype(np.float32)


__all__ = ['build_pyramid', 'shi_tomasi_score', 'multiscale_corners', 'small_blurry_image',
           'DEFAULT_MIN_SCORE']
