"""What no causal estimator can remove from a rotation_sweep seed's heading: the hand's sway.

The hybrid filter takes gravity in the panorama frame as a weighted mean of the specific force
(:mod:`..core.world_alignment`), and a mean of the hand's linear acceleration over [0, T] is
(v(T) - v(0)) / T: it vanishes as the session grows, but over the first second a sway of
0.5-1.2 Hz has not completed one period and its acceleration is all but a constant. A tilt
error tilts the horizontal plane the field is projected on; the error of the estimate is then
a rotation about the field vector (which leaves every magnetometer sample as it was), i.e. a
heading error of about ``tan(dip)`` times the tilt about the north axis (2x at a dip of 64 deg).

:func:`hand_motion_floor` computes that error for one seed: the gravity estimate of the
alignment's own weights (windows and ramps of :class:`WorldAlignmentConfig`) fed with the
simulator's exact hand sway - the part of the phone's acceleration that no rotation explains
(the orbit about the body, which the estimator's lever-arm model takes out, is left out) - and
R_PN built from it and the exact field by eq. 3-4, applied to the true camera orientation.
Everything else (rotation, field, hard and soft iron, noise, disturbances) is perfect, so the
result is a lower bound on the heading RMSE of this estimator on the seed. Reads the simulator's
internals: for benches only.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..core.rotations import heading_tilt_error_deg
from ..core.world_alignment import WorldAlignmentConfig
from ..sim import rotation_sweep as rs

Array = NDArray[np.float64]

#: Sample step of the floor's computation, s (the estimate changes slowly next to it).
STEP_S = 0.01


def ramped_running_mean(t_s: Array, x: Array, window_s: float, ramp_s: float) -> Array:
    """At every sample, the mean of ``x`` so far with the alignment's gravity weights: windows of
    ``window_s`` and a weight ramp of ``ramp_s`` at both ends (at most half the windows), the
    open window weighed like a closed one (``WorldAlignment._solve_gravity``)."""
    widx = np.floor((t_s - t_s[0]) / window_s).astype(int)
    n_windows = int(widx[-1]) + 1
    sums = np.zeros((n_windows, x.shape[1]))
    counts = np.zeros(n_windows)
    out = np.empty_like(x)
    for i, k in enumerate(widx):
        sums[k] += x[i]
        counts[k] += 1
        open_k = k + 1
        ramp = max(1.0, min(open_k / 2.0, ramp_s / window_s))
        idx = np.arange(open_k) + 0.5
        w = np.minimum(1.0, np.minimum(idx, open_k - idx) / ramp)
        out[i] = (w @ sums[:open_k]) / (w @ counts[:open_k])
    return out


def _enu_from_up_and_field(up: Array, field: Array) -> Array:
    """Rotation whose columns are east, north, up (eq. 3-4: up, east = field x up, north =
    up x east) for each row of ``up`` and one field vector; the identity when both are true."""
    up = up / np.linalg.norm(up, axis=1, keepdims=True)
    east = np.cross(field, up)
    east /= np.linalg.norm(east, axis=1, keepdims=True)
    north = np.cross(up, east)
    return np.stack([east, north, up], axis=-1)


def hand_motion_floor(seed: int, duration_s: float = 40.0, session: str = 'authoring',
                      split_s: float = 2.0, config: WorldAlignmentConfig | None = None) -> dict[str, Any]:
    """Heading and tilt RMSE (deg) that the hand's sway alone leaves in the hybrid's estimate of
    a rotation_sweep seed of the default profile (module docstring): over the whole run and
    before / after ``split_s``."""
    c = config or WorldAlignmentConfig()
    scn = rs.make_scenario(seed, session, duration_s)
    t = np.arange(0.0, duration_s, STEP_S)
    sway = np.stack([axis.eval(t, 2) for axis in scn.trajectory.hand], axis=-1)  # ENU, m/s^2
    up = ramped_running_mean(t, sway + np.array([0.0, 0.0, rs.GRAVITY_M_S2]), c.window_s, c.gravity_ramp_s)
    # The estimated ENU axes in true ENU coordinates: a camera whose true orientation is R is
    # estimated as R_axes^T R, whatever R is, so the world-frame error is R_axes^T.
    R_axes = _enu_from_up_and_field(up, scn.earth.vector_enu)
    _, heading, tilt = heading_tilt_error_deg(np.swapaxes(R_axes, 1, 2), np.eye(3))
    heading, tilt = np.atleast_1d(heading), np.atleast_1d(tilt)
    early = t < split_s

    def rms(x: Array) -> float | None:
        return round(float(np.sqrt(np.mean(np.square(x)))), 4) if x.size else None

    return {
        'heading_rmse_deg': rms(heading), f'heading_rmse_deg_first_{split_s:g}s': rms(heading[early]),
        f'heading_rmse_deg_after_{split_s:g}s': rms(heading[~early]), 'tilt_rmse_deg': rms(tilt),
        'dip_deg': round(math.degrees(scn.earth.dip_rad), 2),
    }


def floor_table(seeds: range | list[int], duration_s: float = 40.0) -> dict[str, Any]:
    """:func:`hand_motion_floor` of each seed and the median over them."""
    rows = {str(s): hand_motion_floor(s, duration_s) for s in seeds}
    heading = [r['heading_rmse_deg'] for r in rows.values()]
    first = [r['heading_rmse_deg_first_2s'] for r in rows.values()]
    return {'per_seed': rows, 'summary': {
        'seeds': len(rows), 'heading_rmse_deg_median': round(float(np.median(heading)), 4),
        'heading_rmse_deg_max': round(float(np.max(heading)), 4),
        'heading_rmse_deg_first_2s_median': round(float(np.median(first)), 4),
        'seeds_above_0_5_deg': int(sum(h > 0.5 for h in heading))}}
