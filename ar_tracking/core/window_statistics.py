"""Robust statistics over short time windows of samples, for estimators that keep only sums.

:class:`WindowSums` keeps the per-window sums of the normal equations of a least-squares
problem, so that a robust solve (per-window weights) costs O(windows), not O(samples); samples
kept as flat rows of Python floats are added to them as matrix products (:func:`add_rotated_rows`);
:func:`shorth` and :func:`cauchy_about_medians` give the robust centre, spread and weights of
per-window values. Used by :mod:`.world_alignment` (Langlotz 2011 sec. 5, the panorama's place
in the world).
"""
from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import NDArray
from scipy.special import erfinv

Array = NDArray[np.float64]


def row_medians(x: Array) -> Array:
    """The median of each row of x (k, n), as ``np.median(x, axis=1)`` computes it (the mean of
    the two middle values), without its per-call overhead (~130 -> ~15 us for a few hundred
    values; the partition of a copy in place, as np.partition does, without its wrapper)."""
    n = x.shape[1]
    lo, hi = (n - 1) // 2, n // 2
    part = x.copy()
    part.partition([lo, hi] if hi != lo else lo, axis=1)
    return (part[:, lo] + part[:, hi]) / 2.0


def median(x: Array) -> float:
    """The median of a 1-D array as ``np.median`` gives it, NaN for an empty array or one that
    holds a NaN (:func:`row_medians` of its one row); also the parallax fit's (annotations)."""
    x = np.asarray(x, dtype=float).reshape(-1)
    if x.size == 0 or np.isnan(x).any():
        return math.nan
    return float(row_medians(x[None, :])[0])


def cauchy_about_medians(x: Array, floors: tuple[float, ...], scale: float) -> Array:
    """Cauchy weights of each row of x (k, n) about its median, with the row's robust sigma
    (1.4826 MAD, at least ``floors[i]`` for row i) times ``scale`` as the Cauchy width; all
    rows at once (numpy's per-call cost is most of the cost at a few hundred values)."""
    dev = np.abs(x - row_medians(x)[:, None])
    mad = row_medians(dev).tolist()
    width = np.array([scale * max(1.4826 * m, f) for m, f in zip(mad, floors)])
    return 1.0 / (1.0 + (dev / width[:, None]) ** 2)


def shorth(x: Array, share: float = 0.5) -> tuple[float, float]:
    """Centre and robust sigma of the densest ``share`` of x: the shortest interval that holds
    that share of the values (Rousseeuw's shorth / least median of squares location for one
    half). Unlike the median it sits in the larger of two clusters instead of between them;
    with a share below one half its width is not inflated by a second cluster as large as the
    first (a half of two equal clusters spans both). The width is scaled to a normal sigma."""
    xs = x.copy()  # np.sort(x), without its wrapper
    xs.sort()
    n = len(xs)
    h = min(n, max(2, int(n * share) + 1))
    widths = xs[h - 1:] - xs[:n - h + 1]
    i = int(widths.argmin())
    # The mean as np.mean computes it (pairwise sum / count), without its per-call overhead.
    return float(xs[i:i + h].sum() / h), float(widths[i]) / _normal_width(min(h / n, 0.999))


@functools.lru_cache(maxsize=4096)
def _normal_width(p: float) -> float:
    """Width, in sigmas, of a normal's central share p: 2 sqrt(2) erfinv(p) (cached: scipy's
    ufunc costs a few microseconds per scalar call, and a solve asks for the same few shares)."""
    return 2.0 * math.sqrt(2.0) * float(erfinv(p))


class WindowSums:
    """Sums of samples per time window of ``window_ns`` (stamps), in preallocated arrays whose
    last used row is the open window; neighbours are merged two by two past ``max_windows``.
    ``shapes`` names the summed quantities and their shapes; ``n`` counts the samples."""

    def __init__(self, window_ns: int, max_windows: int, shapes: dict[str, tuple[int, ...]]) -> None:
        self.window_ns = window_ns
        self.max_windows = max_windows
        self.n = np.zeros(64)
        self.sums = {k: np.zeros((64,) + shape) for k, shape in shapes.items()}
        self.count = 0  # windows used, the open one included
        self.end_ns: int | None = None

    def open(self, t_ns: int) -> int:
        """Index of the window that takes a sample at t_ns (a new one when t_ns is past the
        open window's end)."""
        if self.end_ns is None or t_ns >= self.end_ns:
            if self.end_ns is None:
                self.end_ns = t_ns + self.window_ns
            else:
                self.end_ns += self.window_ns * ((t_ns - self.end_ns) // self.window_ns + 1)
            if self.count == len(self.n):
                if self.count >= self.max_windows:
                    self._merge_pairs()
                else:
                    self.n = np.concatenate([self.n, np.zeros(len(self.n))])
                    self.sums = {k: np.concatenate([v, np.zeros_like(v)]) for k, v in self.sums.items()}
            self.count += 1
        return self.count - 1

    def _merge_pairs(self) -> None:
        k = self.count // 2 * 2
        half = (self.count + 1) // 2
        for arr in [self.n] + list(self.sums.values()):
            merged = arr[0:k:2] + arr[1:k:2]
            if self.count % 2:
                merged = np.concatenate([merged, arr[k:k + 1]])
            arr[:half] = merged
            arr[half:] = 0
        self.count = half

    def arrays(self) -> tuple[Array, dict[str, Array]]:
        """Counts and sums of the windows so far (views)."""
        k = self.count
        return self.n[:k], {name: v[:k] for name, v in self.sums.items()}


def weighted_sum(w: Array, M: Array) -> Array:
    """sum_k w_k M_k of a stack of 3x3 matrices, as one matrix-vector product."""
    return w.dot(M.reshape(len(M), 9)).reshape(3, 3)


def flat_rows(flat: list[float], width: int) -> Array:
    """Samples kept as one flat list of floats, ``width`` per sample, as an (n, width) array."""
    return np.fromiter(flat, float, len(flat)).reshape(-1, width)


def add_rotated_rows(ws: WindowSums, k: int, flat: list[float], name: str, x_name: str) -> Array:
    """Add samples kept as flat rows of 12 floats (R_pano_imu row-major, then a vector x in the
    IMU frame) to window k: its count, S = sum R_imu_P, ``name`` = sum R_P_imu x and ``x_name`` =
    sum x. Returns the x, (n, 3). The sums are matrix products over the rows (batched einsums
    cost more); S and sum x are one reduction over the rows (numpy adds rows in order along
    axis 0, so each column's sum is the one a reduction of that column alone gives)."""
    arr = flat_rows(flat, 12)
    R, x = arr[:, :9], arr[:, 9:12]
    ws.n[k] += len(arr)
    total = arr.sum(axis=0)
    sums = ws.sums
    sums['S'][k] += total[:9].reshape(3, 3).T
    sums[x_name][k] += total[9:]
    # sum_n R_n x_n: entry i is sum_j of (R^T x)[(i, j), j], the columns 0, 4, 8 of (R^T x)
    # as (3, 9), added in the order trace(axis1=1, axis2=2) adds them.
    Rtx = R.T.dot(x).reshape(3, 9)
    sums[name][k] += Rtx[:, 0] + Rtx[:, 4] + Rtx[:, 8]
    return x
