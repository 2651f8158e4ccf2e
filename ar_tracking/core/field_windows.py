"""The field windows of the world alignment's robust solve (Langlotz 2011 sec. 5, the panorama's
place in the world, :mod:`.world_alignment`), prepared once per solve.

A field solve judges its windows three times (the held hard iron's fit, then each IRLS
iteration's) and forms the soft-iron normal equations twice; every pass reads the same per-window
means of the sums and the same heading basis about up. :class:`FieldWindows` forms those once,
and each pass is a few whole-array products: over a few hundred windows numpy's per-call cost,
not arithmetic, is most of what a solve pays. No ROS here.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .field_clusters import choose_cluster
from .window_statistics import cauchy_about_medians, shorth
from .world_alignment_config import WorldAlignmentConfig

Array = NDArray[np.float64]
_DIP_FLOOR = math.radians(0.25)  # of the windows' dip sigma


def heading_basis(up: Array) -> tuple[Array, Array]:
    """Two horizontal unit vectors (e1, e2 = up x e1) fixed in the panorama frame, in which the
    headings of field vectors about ``up`` (unit) are measured: x (or y when up is near x) with
    its part along up removed. (On Python floats: a few numpy calls would cost more.)"""
    u0, u1, u2 = np.asarray(up, dtype=float).tolist()
    a0, a1, a2 = 1.0 - u0 * u0, -u0 * u1, -u0 * u2
    if a0 * a0 + a1 * a1 + a2 * a2 < 1e-6:
        a0, a1, a2 = -u1 * u0, 1.0 - u1 * u1, -u1 * u2
    norm = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    a0, a1, a2 = a0 / norm, a1 / norm, a2 / norm
    return np.array((a0, a1, a2)), np.array((u1 * a2 - u2 * a1, u2 * a0 - u0 * a2, u0 * a1 - u1 * a0))


class FieldWindows:
    """One field solve's windows: counts ``n_w``, sums S = sum R_imu_P and Rtm = sum R_P_imu m
    (field relative to |B|) per window, and the up direction of the panorama frame."""

    def __init__(self, n_w: Array, S_w: Array, Rtm_w: Array, up: Array) -> None:
        self.up = up
        self.S_mean = S_w / n_w[:, None, None]
        self.Rtm_mean = Rtm_w / n_w[:, None]
        # S_mean stacked as rows (window, row) and its transposes likewise: S_mean v and
        # S_mean^T v for all windows are then one matrix-vector product each.
        self._rows = self.S_mean.reshape(-1, 3)
        self._rows_t = np.ascontiguousarray(self.S_mean.transpose(0, 2, 1)).reshape(-1, 3)
        self.e1, self.e2 = heading_basis(up)
        self._basis = np.array((self.e1, self.e2, up)).T  # columns e1, e2, up
        #: The doubt between the chosen field cluster and the runner-up, of the last :meth:`weights`.
        self.ambiguity_var = 0.0

    def heading(self, f: Array) -> float:
        """Heading of f about up in the basis of :func:`heading_basis` (rad)."""
        return math.atan2(float(f.dot(self.e2)), float(f.dot(self.e1)))

    def mean_fields(self, f: Array, h: Array, E: Array | None) -> Array:
        """Per window, the field in the panorama frame it implies with hard iron h and soft
        iron E (None: not modelled): mean R_P_imu (m - h) - S^T E S f with S the window's mean
        R_imu_P (the soft-iron term at the mean rotation, as the normal equations take it)."""
        if E is None:
            return self.Rtm_mean - self._rows_t.dot(h).reshape(-1, 3)
        z = self._rows.dot(f).reshape(-1, 3).dot(E.T) + h  # h + E S f per window
        return self.Rtm_mean - np.einsum('nji,nj->ni', self.S_mean, z)

    def weights(self, f: Array, h: Array, E: Array | None, heading_mode: float | None,
                config: WorldAlignmentConfig) -> tuple[Array, float]:
        """Cauchy weights of the windows (heading, strength and dip of the field each implies
        in the panorama frame, about their medians) and the heading spread (rad). ``E``: the
        residual soft iron of the fit being judged (None: not modelled); ``heading_mode``: the
        heading of the cluster the last solve chose (None: none yet). Sets
        :attr:`ambiguity_var`."""
        c = config
        mean_f = self.mean_fields(f, h, E)
        along = mean_f.dot(self._basis)  # components along e1, e2 and up
        # Headings about up relative to f's.
        f_abs = self.heading(f)
        # ((psi - f_abs + pi) mod 2 pi) - pi, each step in place (one array instead of five).
        rel = np.arctan2(along[:, 1], along[:, 0])
        rel -= f_abs
        rel += math.pi
        np.remainder(rel, 2.0 * math.pi, out=rel)
        rel -= math.pi
        centre, spread = shorth(rel, c.cluster_share)
        spread = max(spread, math.radians(0.25))
        width = c.cauchy_scale * spread
        prev = None if heading_mode is None else (heading_mode - f_abs + math.pi) % (2.0 * math.pi) - math.pi
        centre, self.ambiguity_var = choose_cluster(rel, centre, prev, width, c)
        off = rel - centre
        dev = np.abs(off)
        w_psi = off / width  # 1 / (1 + (off / width)^2), in place
        w_psi *= w_psi
        w_psi += 1.0
        np.divide(1.0, w_psi, out=w_psi)
        # Past reject_widths the weight is zero, not a Cauchy tail: a tail still lets the hard
        # iron drift towards a disturbance, which then looks like the clean field (with little
        # rotation a field offset fixed in the phone and one fixed in the world look alike).
        w_psi[dev > c.reject_widths * width] = 0.0
        # Most real disturbances also change the field's strength or dip: a window whose mean
        # field departs in either is down-weighted too (a turn that keeps both is left to the
        # heading test).
        norm_dip = np.empty((2, len(rel)))
        # |mean_f| per window: the columns' squares added in the order np.add.reduce(axis=1)
        # adds them (the same values; a reduction over rows of three costs ~10 us at 400 windows).
        sq = mean_f * mean_f
        norm = np.sqrt(sq[:, 0] + sq[:, 1] + sq[:, 2], out=norm_dip[0])
        sin_dip = -along[:, 2] / np.maximum(norm, 1e-12)
        np.arcsin(np.minimum(np.maximum(sin_dip, -1.0), 1.0), out=norm_dip[1])  # clipped to [-1, 1]
        w_norm, w_dip = cauchy_about_medians(norm_dip, (0.005, _DIP_FLOOR), c.cauchy_scale)
        return w_psi * w_norm * w_dip, spread
