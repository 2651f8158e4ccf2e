"""Exposure correction of the EDR map (Langlotz 2011 sec. 4.1): the keypoint-pair estimates
filtered over frames (:class:`ExposureFilter`), and the fit of a gain and an offset on the
frame's whole overlap with the map (:func:`fit_overlap_exposure`, the mapper's default).

Sec. 4.1 corrects each frame by "the average difference" of the intensities of its matched
keypoint pairs (map minus frame). Auto-exposure is a gain on the encoded values (for a power-
law encoding, a gain g on linear radiance is g^(1/gamma) on the 8-bit values), so the
difference that is the same for every pixel of a frame is the difference of *log*
intensities: ``log_gain`` of :class:`~.tracker.TrackResult`; the frame is mapped as
``exp(c) * I``. A single additive offset is right only at the keypoints' mean brightness and
leaves steps of (g - 1) * (I - mean) elsewhere.

Each frame's estimate is the mean of some 20-60 pairs and carries their noise (standard error
``se``, a few 0.1 % of the gain); corrected independently, consecutive frames would differ by
that noise and every frame boundary in the map would become a small seam, although the
exposure between consecutive frames rarely changes. The exposure of a phone camera is piecewise
constant (jumps, within ~0.1 s) with a slow drift, which this 1-D filter models on
``c`` = log correction:

* between frames ``c`` is a random walk with variance ``drift_per_s ** 2 * dt`` (the drift);
* a measurement ``z`` with variance ``se ** 2 + floor ** 2`` updates it (Kalman);
* a measurement outside ``gate`` standard deviations of the prediction is an exposure jump:
  ``c`` restarts from it.

The first frame is the baseline: ``c = 0`` with no uncertainty.

The same filter smooths the additive correction of the default ``edr_correction='offset'``
(the paper's "average difference", 8-bit units; :data:`OFFSET_EXPOSURE`). Unsmoothed, each
frame's offset carries its own estimation noise (about 0.3 levels between consecutive frames
on the 60 s rotation_sweep bags while the exposure did not change), and since every frame
contributes a sliver of the map, that noise becomes a step at almost every contribution
boundary - seams that EDR itself adds and the 8-bit map does not have. ``smooth=False`` gives
the paper's literal per-frame correction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class ExposureConfig:
    #: Random-walk rate of the log gain between jumps, 1/sqrt(s) (slow auto-exposure drift).
    drift_per_s: float = 0.01
    #: Added to each frame's standard error (patch misalignment that the spread does not show).
    floor: float = 0.002
    #: Innovations beyond this many standard deviations are exposure jumps (restart).
    gate: float = 4.0
    #: False: every frame's own estimate is used (no smoothing, as sec. 4.1 literally says).
    smooth: bool = True


#: The filter for the additive offset (8-bit units): the log-gain defaults scaled by a mid-grey
#: level of 128 (an offset x at mid-grey is the log gain x / 128).
OFFSET_LEVEL = 128.0
OFFSET_EXPOSURE = ExposureConfig(drift_per_s=0.01 * OFFSET_LEVEL, floor=0.002 * OFFSET_LEVEL)


class ExposureFilter:
    """Correction state, log gain or offset (see the module docstring). Deterministic, one caller."""

    def __init__(self, config: ExposureConfig | None = None) -> None:
        self.config = config or ExposureConfig()
        self.reset()

    def reset(self) -> None:
        self.log_gain = 0.0
        self.var = 0.0
        self.jumps = 0

    def update(self, z: float, se: float, dt_s: float) -> float:
        """Fold in one frame's estimate ``z`` (log map - log frame, or map - frame for the
        offset) with standard error ``se`` taken ``dt_s`` after the previous frame; returns the
        frame's correction."""
        cfg = self.config
        var_pred = self.var + cfg.drift_per_s ** 2 * max(dt_s, 0.0)
        if not math.isfinite(se) or not math.isfinite(z):
            self.var = var_pred
            return self.log_gain
        r = se * se + cfg.floor * cfg.floor
        if not cfg.smooth:
            self.log_gain, self.var = z, r
            return z
        nu = z - self.log_gain
        s = var_pred + r
        if nu * nu > cfg.gate * cfg.gate * s:
            self.log_gain, self.var = z, r
            self.jumps += 1
        else:
            k = var_pred / s
            self.log_gain += k * nu
            self.var = (1.0 - k) * var_pred
        return self.log_gain


@dataclass(frozen=True)
class OverlapExposureConfig:
    """The frame-to-map photometric fit of ``edr_correction='overlap'`` (:func:`fit_overlap_exposure`)."""

    #: Grid step (map pixels) of the overlap samples (4: no better on the 60 s bags, 8: worse).
    step_px: int = 6
    #: Samples whose residual exceeds this many robust standard deviations are dropped (refits).
    trim_sigmas: float = 2.5
    #: Least-squares fits, each after trimming around the previous one.
    iterations: int = 3
    #: Frame values at or beyond these 8-bit levels are clipped, not exposed: not used.
    dark: float = 3.0
    bright: float = 252.0
    #: Fewer usable samples than this: no fit (the mapper falls back to the keypoint offset).
    min_samples: int = 50
    #: Gains outside [1 / max_gain, max_gain] are failed fits.
    max_gain: float = 4.0


def _trimmed(a: NDArray[np.float32], f: NDArray[np.float32], usable: NDArray[np.bool_],
             keep: NDArray[np.bool_], gain: float, offset: float, sigmas: float) -> NDArray[np.bool_]:
    """The usable samples within ``sigmas`` robust standard deviations (1.4826 x the median
    absolute residual of the ``keep`` samples; at least 0.5 levels) of ``gain * f + offset``."""
    res = np.abs(a - np.float32(gain) * f - np.float32(offset))
    kept = res[keep]
    if kept.size == 0:
        return keep
    scale = 1.4826 * float(np.partition(kept, kept.size // 2)[kept.size // 2])
    return usable & (res <= np.float32(max(sigmas * scale, 0.5)))


def fit_overlap_exposure(map_values: NDArray[np.floating], frame_values: NDArray[np.floating],
                         config: OverlapExposureConfig | None = None,
                         initial: tuple[float, float] | None = None) -> tuple[float, float] | None:
    """(gain, offset) with ``map ~ gain * frame + offset`` over the frame's overlap with the map
    (an extension of sec. 4.1), None when the overlap cannot support it.

    Sec. 4.1 corrects a frame by the mean intensity difference of its matched keypoint pairs:
    one offset from 20-60 patches at corners, where sub-pixel misalignment moves the means most.
    Every pixel of the frame that falls on the mapped part of the map is such a pair; fitted on
    all of them, the correction has two terms: a gain (auto-exposure scales the encoded values;
    a single offset is right only at the mean brightness and leaves steps of (g - 1) * (I - mean)
    at brighter or darker pixels) and an offset (additive veiling glare, black-level drift).
    Least squares, refitted ``iterations`` times without the samples beyond ``trim_sigmas``
    robust standard deviations (edges misaligned by a fraction of a pixel, moving objects);
    clipped frame values are excluded. The frame is then mapped as ``gain * I + offset``: it
    continues the map's levels, the first frame's being the baseline.

    ``initial`` (gain, offset), e.g. the previous frame's: the first trim is taken around it,
    which saves one of the ``iterations`` fits (consecutive frames differ little)."""
    cfg = config or OverlapExposureConfig()
    a = np.asarray(map_values, np.float32)
    f = np.asarray(frame_values, np.float32)
    usable = (f > cfg.dark) & (f < cfg.bright) & np.isfinite(a)
    keep = usable
    fits = max(cfg.iterations, 1)
    if initial is not None:
        keep = _trimmed(a, f, usable, usable, initial[0], initial[1], cfg.trim_sigmas)
        fits = max(fits - 1, 1)
    gain, offset = 1.0, 0.0
    for it in range(fits):
        n = int(np.count_nonzero(keep))
        if n < cfg.min_samples:
            return None
        # Least squares of a = gain * f + offset (2 x 2 normal equations, float64 sums).
        fk, ak = f[keep].astype(np.float64), a[keep].astype(np.float64)
        sf, sa = fk.sum(), ak.sum()
        sff, sfa = float(fk @ fk), float(fk @ ak)
        det = n * sff - sf * sf
        if not det > 1e-9 * n * n:
            return None  # no spread of intensities: the gain is not determined
        gain = (n * sfa - sf * sa) / det
        offset = (sa - gain * sf) / n
        if it + 1 < fits:
            keep = _trimmed(a, f, usable, keep, gain, offset, cfg.trim_sigmas)
    if not (math.isfinite(gain) and math.isfinite(offset)) or not 1 / cfg.max_gain <= gain <= cfg.max_gain:
        return None
    return float(gain), float(offset)
