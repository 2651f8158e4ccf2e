"""The panorama's place in the world, R_PN of Langlotz 2011 sec. 5, from a whole session of samples.

Eq. 1-2 of the paper: ``R_DP R_PN = R_DN`` - the visual tracker gives the camera in the panorama
frame (R_DP), the sensors give it in the world (R_DN), and the panorama frame itself does not move,
so R_PN is one constant rotation. The paper estimates it with an EKF on per-sample tilt-compass
readings (eq. 5-6; our first version of this node did the same); a reading carries the
whole error of its sample (hand acceleration tilts it, a turned field or residual iron turns it),
and the filter's result stays an almost constant offset of 1-3 degrees on hard data.

Here the raw sensor vectors are carried into the panorama frame instead, where the quantities
they measure are constant, and two small least-squares problems are solved over everything
seen since the panorama started:

* **gravity**: ``a_imu(t) = R_imu_P(t) g_P + b_a + e(t)``. The hand's linear acceleration is
  part of e(t), and in the (inertial) panorama frame its mean over the session is the change of
  velocity divided by the time (``(v(T) - v(0)) / T``): it vanishes as the session grows, whatever
  its size - so no gating on |a| ~ g is needed (gating on |a| ~ g or on a low rotation rate was
  tried and made the tilt worse on the hard simulator profile). The weights of the windows ramp
  up and down over ``gravity_ramp_s`` at both ends of the session, so that the velocity term is
  the mean velocity over the ramps rather than its end values. A person turns the phone about
  their own body, the phone at arm's length: that orbit's acceleration ``alpha x r + omega x
  (omega x r)`` is modelled with the (low-passed) gyro rate and a lever arm r in the IMU frame,
  estimated in the same least squares (linear in r). The accelerometer bias b_a has a ridge
  prior (only its horizontal part is observable, as the phone turns). Sums kept per window.
* **magnetic field**: ``m_imu(t) = (I + E) R_imu_P(t) f_P + h + e(t)``: the local field is a
  constant vector in the panorama frame, h is the residual hard iron and E the residual soft
  iron left by the calibration (:mod:`.soft_iron`); with the panorama's rotations they
  separate (a moving-body magnetometer calibration, linear in (f_P, h) and in E about the last
  f_P). Disturbances that turn the field while keeping its strength and dip - invisible to
  a per-sample check - are outliers here: the estimate is an IRLS with a Cauchy loss on the
  field each short window of samples implies (strength and dip about their medians, heading
  about the densest cluster of window headings, kept from one solve to the next unless another
  cluster clearly outgrows it - a turned field early in a session can hold as many windows as
  the true one, and a median would sit between the two), re-solved every ``solve_period_s``
  from each window's sums (O(1) per sample, O(windows) per solve). A field sample is paired
  with the orientation at its own stamp (:meth:`WorldAlignment.add_field`).

R_PN follows from g_P and f_P by the gravity-first construction of eq. 3-4 (up = g, east =
f x up, north = up x east), with the declination. Its covariance (:mod:`.alignment_covariance`):
tilt from the hand's velocity term, heading from the windows' scatter and the hard iron's bias
through the field solve and the tilt's leak through the dip, plus floors for what the model
leaves out. Field vectors are used in units of their median norm: any magnetometer unit works.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from .alignment_covariance import (FieldErrorParts, field_error_parts, field_heading_mse, hand_tilt_variance,
                                   solve_regular)
from .field_windows import FieldWindows
from .rotations import rot_z
from .soft_iron import soft_iron_normal_equations, symmetric_from_params
from .window_statistics import WindowSums, add_rotated_rows, flat_rows, median, weighted_sum
from .world_alignment_config import WorldAlignmentConfig

__all__ = ['WorldAlignment', 'WorldAlignmentConfig', 'WorldAlignmentEstimate']

Array = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class WorldAlignmentEstimate:
    """R_pano_enu (rotates ENU vectors into the panorama frame) and its uncertainty. (Slots: one
    is made per estimate, and a frozen dataclass with slots is made in about half the time.)"""

    R_pano_enu: Array
    #: Covariance of the error of R_enu_pano in ENU axes (x, y: tilt, z: heading), rad^2.
    covariance_enu: Array
    #: Share of the field windows the robust solve down-weighted below one half (disturbed).
    field_outlier_share: float
    #: Residual hard iron (imu frame, relative to |B|) and accelerometer bias (m/s^2).
    hard_iron: Array
    accel_bias: Array
    #: Residual soft iron E (imu frame, m = (I + E) R f + h; zeros when not modelled).
    soft_iron: Array
    #: The unit of the relative field quantities (h, f): the windows' median |field|, in the
    #: field samples' own unit (tesla for a MagneticField).
    field_scale: float = 1.0


# The cross-product matrix [alpha]x, flat row-major, is alpha.dot(_SKEW): each entry is one
# component of alpha times +-1 (exact; one product instead of fancy-indexed updates).
_SKEW = np.zeros((3, 9))
_SKEW[(2, 1, 2, 0, 1, 0), (1, 2, 3, 5, 6, 7)] = (-1.0, 1.0, 1.0, -1.0, -1.0, 1.0)


def solve_due_after_ns(config: WorldAlignmentConfig, period_ns: int, t_ns: int, t_first_ns: int | None) -> int:
    """Stamps after the last field solve at which the next one is due, for a sample at t_ns of
    a session that began at t_first_ns: min(solve_period, max(0.1 s, share x span)) - at once
    past the full period, never before 0.1 s (when the period is longer), in between by the
    span - and late in a long session long_share x span once that is longer. It never
    decreases as t_ns grows."""
    span_ns = t_ns - (t_ns if t_first_ns is None else t_first_ns)
    period = min(period_ns, max(100_000_000, int(config.solve_period_share * span_ns)))
    return max(period, int(config.solve_period_long_share * span_ns))


class WorldAlignment:
    """Accumulates (R_pano_imu, accel, field) samples and estimates R_pano_enu (module doc)."""

    def __init__(self, config: WorldAlignmentConfig | None = None) -> None:
        self.config = config or WorldAlignmentConfig()
        self.reset()

    def reset(self, prior: tuple[Array, float] | None = None) -> None:
        """Forget every sample. ``prior`` = (R_pano_enu, 1-sigma rad) seeds a new panorama
        with the orientation carried over (e.g. by the gyro) from the previous one."""
        # Gravity: normal equations of [g_P; b_a] as sums.
        self._n = 0
        self._lever = self.config.lever_arm_sigma_m > 0
        self._sum_aa = 0.0
        self._accel_var = 0.25
        self._sum_a_norm = 0.0
        self._t_first_ns: int | None = None
        self._t_last_ns = 0
        # Gravity per window: count, sum R_imu_P, sum R_P_imu a, sum a.
        win_ns = int(self.config.window_s * 1e9)
        self._gw = WindowSums(win_ns, self.config.max_windows, {
            'S': (3, 3), 'Rta': (3,), 'a': (3,),
            'RtK': (3, 3), 'K': (3, 3), 'KtK': (3, 3), 'Kta': (3,)})
        # Samples not yet in their window's sums (rows of floats, see add) and those windows.
        self._g_rows: list[float] = []
        self._lever_rows: list[float] = []
        self._f_rows: list[float] = []
        self._g_window = 0
        self._f_window = 0
        self._solve_period_ns = int(self.config.solve_period_s * 1e9)
        # Low-passed rate and specific force of the lever-arm model (wx, wy, wz, ax, ay, az).
        self._lever_lp: list[float] | None = None
        self._prev_omega_t_ns = 0
        self._lever_arm = np.zeros(3)
        self._lever_count = 0
        self._gravity: tuple[Array, Array] | None = None
        self._gravity_windows = -1
        self._ramp_s = self.config.window_s
        self._field_error: FieldErrorParts | None = None
        # Field: the normal equations of m = (I + E) R_imu_P f + h are sums, so each window keeps its
        # own sums (count, sum R_imu_P, sum R_P_imu m, sum m, sum |m|) and the robust solve
        # works on windows only.
        self._fw = WindowSums(win_ns, self.config.max_windows, {'S': (3, 3), 'Rtm': (3,), 'm': (3,), 'norm': ()})
        self._field_samples = 0
        self._solve_t_ns: int | None = None
        # Stamps [from, until) at which no solve is due (see _add_field); empty at first.
        self._no_solve_from_ns, self._no_solve_until_ns = 1, 0
        self._field: tuple[Array, Array, float, float] | None = None  # f_P, h (relative), sigma, outliers
        self._prior = prior
        self._h_last: Array | None = None
        self._soft_iron = np.zeros((3, 3))
        self._field_scale = 1.0
        self._ambiguity_var = 0.0
        self._heading_mode: float | None = None
        self._field_enu_ref: Array | None = None if prior is None else getattr(self, '_field_enu_ref', None)
        self._estimate: WorldAlignmentEstimate | None = None
        # (solves it was built from, R_pano_enu, |g|, tan dip, field heading variance).
        self._geometry: tuple[tuple[object, ...], Array, float, float, float] | None = None
        self._dirty = True

    # -- samples ---------------------------------------------------------------------------

    def add(self, t_ns: int, R_pano_imu: Array, accel: Array, mag: Array | None = None,
            omega: Array | None = None) -> None:
        """One calibrated IMU sample (specific force, m/s^2; field, any unit; rate, rad/s, for
        the lever-arm model) with the IMU's orientation in the panorama frame at its stamp.

        The sample is kept as Python floats until its window's sums are needed (a window
        closes or a solve reads them): numpy's per-call cost, not arithmetic, is what a
        per-sample update pays; the sums of a window's samples are then a few array products."""
        t_ns = int(t_ns)
        self._n += 1
        if self._t_first_ns is None:
            self._t_first_ns = t_ns
        self._t_last_ns = t_ns
        gw = self._gw
        if gw.end_ns is None or t_ns >= gw.end_ns:  # (otherwise the open window takes it)
            if gw.end_ns is not None:
                self._flush_gravity()
            self._g_window = gw.open(t_ns)
        r = R_pano_imu.ravel().tolist()
        ax, ay, az = np.asarray(accel, dtype=float).tolist()
        rows = self._g_rows
        rows += r
        rows += (ax, ay, az)
        if omega is not None and self._lever:
            self._add_lever_arm(t_ns, r, np.asarray(omega, dtype=float).tolist(), ax, ay, az)
        aa = ax * ax + ay * ay + az * az
        self._sum_aa += aa
        self._sum_a_norm += math.sqrt(aa)
        self._dirty = True
        if mag is not None:
            self._add_field(t_ns, r, mag)

    def add_field(self, t_ns: int, R_pano_imu: Array, mag: Array) -> None:
        """One calibrated field sample (any unit) with the IMU's orientation in the panorama
        frame at its own stamp (a magnetometer has its own rate and stamps)."""
        self._add_field(int(t_ns), R_pano_imu.ravel().tolist(), mag)

    def _add_field(self, t_ns: int, r: list[float], mag: Array) -> None:
        """:meth:`add_field` with R_pano_imu as 9 floats (row-major)."""
        fw = self._fw
        self._dirty = True
        if fw.end_ns is None or t_ns >= fw.end_ns:  # (otherwise the open window takes it)
            if fw.end_ns is not None:
                self._flush_field()
            self._f_window = fw.open(t_ns)
        rows = self._f_rows
        rows += r
        rows += np.asarray(mag, dtype=float).tolist()
        self._field_samples += 1
        solve_t = self._solve_t_ns
        solve = solve_t is None or self._field_samples < 8
        if solve_t is not None and not solve and not self._no_solve_from_ns <= t_ns < self._no_solve_until_ns:
            due_ns = solve_due_after_ns(self.config, self._solve_period_ns, t_ns, self._t_first_ns)
            solve = t_ns - solve_t >= due_ns
            if not solve:
                # The period only grows with the stamp (the span does), so no solve is due
                # before solve_t + this period: the stamps up to there skip the test.
                self._no_solve_from_ns, self._no_solve_until_ns = t_ns, solve_t + due_ns
        if solve:
            self._solve_t_ns = t_ns
            self._no_solve_from_ns, self._no_solve_until_ns = 1, 0
            self._field = self._solve_field()

    def _add_lever_arm(self, t_ns: int, row: list[float], omega: list[float], ax: float, ay: float,
                       az: float) -> None:
        """The lever-arm terms' inputs: a phone turning about a centre at r (IMU frame) feels
        alpha x r + omega x (omega x r) = K r. The person's turn, not the wrist's tremor, carries
        the phone around that centre, so rate and specific force are low-passed alike
        (``lever_arm_tau_s``) and alpha is the difference of the low-passed rate. ``row`` is the
        sample's R_pano_imu (row-major, 9 floats); K and its sums are formed when the window's
        sums are (:meth:`_flush_gravity`)."""
        prev_t = self._prev_omega_t_ns
        lp = self._lever_lp
        if lp is None or not 0 < t_ns - prev_t < 100_000_000:
            self._lever_lp = [*omega, ax, ay, az]
            self._prev_omega_t_ns = t_ns
            return
        dt = (t_ns - prev_t) * 1e-9
        gain = min(1.0, dt / self.config.lever_arm_tau_s)
        wx0, wy0, wz0, ax0, ay0, az0 = lp
        wx, wy, wz = wx0 + gain * (omega[0] - wx0), wy0 + gain * (omega[1] - wy0), wz0 + gain * (omega[2] - wz0)
        ax, ay, az = ax0 + gain * (ax - ax0), ay0 + gain * (ay - ay0), az0 + gain * (az - az0)
        self._lever_lp = [wx, wy, wz, ax, ay, az]
        self._prev_omega_t_ns = t_ns
        self._lever_count += 1
        if self._lever_count % 2:
            return  # every other sample, counted twice: the orbit is slow next to the rate
        # R_pano_imu (9), low-passed specific force (3), rate (3), angular acceleration (3).
        rows = self._lever_rows
        rows += row
        rows += (ax, ay, az, wx, wy, wz, (wx - wx0) / dt, (wy - wy0) / dt, (wz - wz0) / dt)

    def _flush_gravity(self) -> None:
        """Add the kept samples to the open gravity window's sums (S = sum R_imu_P, Rta = sum
        R_P_imu a, a = sum a; with the lever arm K = [alpha]x + [omega]x^2 times 2 per counted
        sample, and RtK = sum R_P_imu K, K, KtK = sum K^T K / 2, Kta = sum K^T a_lp)."""
        if not self._g_rows:
            return
        k, sums = self._g_window, self._gw.sums
        add_rotated_rows(self._gw, k, self._g_rows, 'Rta', 'a')
        self._g_rows = []
        if self._lever_rows:
            lever = flat_rows(self._lever_rows, 18)
            self._lever_rows = []
            n = len(lever)
            R = lever[:, :9].reshape(-1, 3, 3)
            a_lp, w, alpha = lever[:, 9:12], lever[:, 12:15], lever[:, 15:18]
            # K = w w^T - |w|^2 I + [alpha]x, flat row-major per sample, times 2.
            K = (w[:, :, None] * w[:, None, :]).reshape(n, 9)
            K[:, 0::4] -= (w * w).sum(axis=1, keepdims=True)
            K += alpha.dot(_SKEW)
            K *= 2.0
            K_rows = K.reshape(3 * n, 3)  # rows (sample, j) of each K
            # sum R K, sum K, sum K^T K / 2 and sum K^T a_lp as products over the rows.
            sums['RtK'][k] += np.ascontiguousarray(R.transpose(1, 0, 2)).reshape(3, 3 * n).dot(K_rows)
            sums['K'][k] += K.sum(axis=0).reshape(3, 3)
            sums['KtK'][k] += 0.5 * K_rows.T.dot(K_rows)
            sums['Kta'][k] += K_rows.T.dot(a_lp.reshape(3 * n))

    def _flush_field(self) -> None:
        """Add the kept field samples to the open field window's sums (S = sum R_imu_P, Rtm =
        sum R_P_imu m, m = sum m, norm = sum |m|)."""
        if not self._f_rows:
            return
        k, sums = self._f_window, self._fw.sums
        m = add_rotated_rows(self._fw, k, self._f_rows, 'Rtm', 'm')
        self._f_rows = []
        sums['norm'][k] += np.sqrt((m * m).sum(axis=1)).sum()

    def reanchor(self, Q: Array, sigma_rad: float) -> None:
        """A new panorama frame P' = Q P (``Q`` = R_P'P, from the gyro across a tracker restart,
        known to ``sigma_rad``): the windows so far are turned into P' instead of forgotten, so
        the hard iron, the field's clusters and gravity keep their history. They are weighted
        down to what a prior known to sigma_rad is worth (:meth:`_prior_weight`) when they hold
        more than that: an error of Q would otherwise stay in the estimate for as long again.
        Beyond ``reanchor_max_sigma_rad`` (or before any estimate): :meth:`reset` with a prior."""
        Q = np.asarray(Q, dtype=float)
        c = self.config
        if sigma_rad > c.reanchor_max_sigma_rad or not self.ready:
            estimate = self.estimate()
            self.reset(prior=None if estimate is None else (Q @ estimate.R_pano_enu, sigma_rad))
            return
        self._flush_gravity()
        self._flush_field()
        alpha = 1.0
        if self._field_samples > 0:
            alpha = min(1.0, self._prior_weight(sigma_rad, c.field_model_sigma, 1.0) / self._field_samples)
        # S sums R_imu_P (R_imu_P' = R_imu_P Q^T); Rta, RtK, Rtm sum R_P_imu x (R_P'_imu x =
        # Q R_P_imu x); the rest are in the IMU frame.
        for ws, turned in ((self._gw, ('Rta', 'RtK')), (self._fw, ('Rtm',))):
            k = ws.count
            ws.n[:k] *= alpha
            ws.sums['S'][:k] = ws.sums['S'][:k] @ Q.T
            for name in turned:
                ws.sums[name][:k] = np.einsum('ij,kj...->ki...', Q, ws.sums[name][:k])
            for v in ws.sums.values():
                v[:k] *= alpha
        self._n = max(1, int(round(self._n * alpha))) if self._n else 0
        self._sum_aa *= alpha
        self._sum_a_norm *= alpha
        if self._prior is not None:
            self._prior = (Q @ self._prior[0], self._prior[1])
        self._gravity, self._gravity_windows = None, -1
        self._heading_mode = None
        self._estimate, self._geometry, self._dirty = None, None, True
        if self._field is not None:
            f, h, sigma, outliers = self._field
            self._field = (Q @ f, h, sigma, outliers)
            self._field = self._solve_field()

    def set_declination(self, declination_rad: float) -> None:
        """Change the magnetic declination (true north = magnetic north turned by it); the
        samples so far stay, the next estimate uses it."""
        self.config = replace(self.config, declination_rad=float(declination_rad))
        self._dirty = True

    def up_in_panorama(self) -> Array | None:
        """The gravity solve's up direction in the panorama frame (None before any sample)."""
        return self._up_estimate() if self._n > 0 else None

    @property
    def ready(self) -> bool:
        return self._n > 0 and self._field is not None

    # -- solves ----------------------------------------------------------------------------

    def _prior_weight(self, sigma_rad: float, noise: float, scale: float) -> float:
        """Samples' worth of a prior vector known to sigma_rad, against per-sample noise whose
        errors are correlated over ``correlation_s`` (so the prior is set against correlation
        times of data, not single samples)."""
        span_s = 0.0 if self._t_first_ns is None else (self._t_last_ns - self._t_first_ns) * 1e-9
        per_corr = self._n / span_s * self.config.correlation_s if span_s > 0.5 else 100.0
        return (noise / max(scale * sigma_rad, 1e-9)) ** 2 * per_corr

    def _solve_gravity(self) -> tuple[Array, Array]:
        """[g_P; b_a] from the window sums, tapered at both ends of the session (module docstring),
        with the ridge on b_a (and the prior). Re-solved when a window has closed."""
        closed = self._gw.count - 1  # the open window changes with every sample
        if self._gravity is not None and self._gravity_windows == closed and closed >= 4:
            return self._gravity
        self._flush_gravity()
        c = self.config
        n_w, sums = self._gw.arrays()
        S_w, Rta_w, a_w = sums['S'], sums['Rta'], sums['a']
        k = len(n_w)
        ramp = max(1.0, min(k / 2.0, c.gravity_ramp_s / c.window_s))
        self._ramp_s = ramp * c.window_s
        idx = np.arange(k) + 0.5
        w = np.minimum(1.0, np.minimum(idx, k - idx) / ramp)
        n = float(w.dot(n_w))
        sum_R = weighted_sum(w, S_w)
        sum_Rta = w.dot(Rta_w)
        sum_a = w.dot(a_w)
        g_mag = self._sum_a_norm / self._n
        # Per-sample noise of the model, for the ridge weight: the scatter of |a| about g.
        var = max(self._accel_var, 0.05 ** 2)
        lam_b = var / c.accel_bias_sigma_m_s2 ** 2
        lever = c.lever_arm_sigma_m > 0
        dim = 9 if lever else 6
        A = np.zeros((dim, dim))
        diag = A.reshape(-1)[::dim + 1]  # a view of A's diagonal (basic slices cost less than index arrays)
        diag[:3] = n
        A[:3, 3:6] = sum_R.T
        A[3:6, :3] = sum_R
        diag[3:6] = n + lam_b
        rhs = np.zeros(dim)
        rhs[:3], rhs[3:6] = sum_Rta, sum_a
        if lever:
            RtK = weighted_sum(w, sums['RtK'])
            K = weighted_sum(w, sums['K'])
            A[:3, 6:] = RtK
            A[6:, :3] = RtK.T
            A[3:6, 6:] = K
            A[6:, 3:6] = K.T
            A[6:, 6:] = weighted_sum(w, sums['KtK'])
            diag[6:9] += var / c.lever_arm_sigma_m ** 2
            rhs[6:] = w.dot(sums['Kta'])
        if self._prior is not None:
            R_pe, sigma = self._prior
            wp = self._prior_weight(sigma, math.sqrt(var), g_mag)
            diag[:3] += wp
            rhs[:3] += wp * (R_pe @ np.array([0.0, 0.0, g_mag]))
        x = solve_regular(A, rhs)
        g, b = x[:3], x[3:6]
        if lever:
            self._lever_arm = x[6:]
        self._gravity = (g, b)
        self._gravity_windows = closed
        n = float(self._n)
        # Per-axis residual variance of a - R g - b from the sums (the hand's acceleration and
        # the sensor noise): it weighs the ridge of the next solve and sets the covariance.
        all_R, all_Rta, all_a = S_w.sum(axis=0), Rta_w.sum(axis=0), a_w.sum(axis=0)
        sq = (self._sum_aa - 2.0 * g.dot(all_Rta) - 2.0 * b.dot(all_a) + n * g.dot(g)
              + 2.0 * g.dot(all_R.T.dot(b)) + n * b.dot(b))
        self._accel_var = max(sq / (3.0 * n), 0.0)
        return g, b

    def _solve_field(self) -> tuple[Array, Array, float, float]:
        """Robust fit of m = (I + E) R_imu_P f_P + h (ridges on h and E), over windows of ``window_s``.

        A disturbance lasts seconds and turns the field for all of its samples at once, so the
        samples are grouped in short windows (``window_s``): each window gives the heading
        of the field it implies in the panorama frame, the windows' headings are compared with
        the cluster :func:`.field_clusters.choose_cluster` takes as the Earth's field, and a window
        that departs gets a Cauchy weight for all its samples (this survives up to half of the
        windows disturbed; a per-sample loss started from least squares does not, once a long
        disturbance has pulled the fit). f_P and h are
        then refitted by weighted least squares (E linearised about the previous f_P, see
        :mod:`.soft_iron`). The normal equations are sums, so only the
        windows' sums are kept. Returns f_P, h (relative to |B|), the residual sigma of the
        window headings (rad) and the share of windows weighted below one half."""
        c = self.config
        self._flush_field()
        n_w, sums = self._fw.arrays()
        S_w, Rtm_w, m_w, norm_w = sums['S'], sums['Rtm'], sums['m'], sums['norm']
        scale = median(norm_w / n_w)
        if scale <= 0 or not math.isfinite(scale):
            scale = 1.0
        self._field_scale = scale
        Rtm_w = Rtm_w / scale
        m_w = m_w / scale
        Rtm_m_w = np.concatenate((Rtm_w, m_w), axis=1)  # the right-hand side's sums, side by side
        n_win = len(n_w)
        w_win = np.ones(n_win)
        prior = None
        if self._prior is not None and self._field_enu_ref is not None:
            prior = self._prior[0] @ self._field_enu_ref
        windows = FieldWindows(n_w, S_w, Rtm_w, self._up_estimate())
        spread = math.radians(2.0)
        outliers = 0.0
        # The windows are first judged with the previous hard iron held (zero at the start):
        # a joint least-squares start would let h absorb a disturbance - with little rotation a
        # field offset fixed in the world and one fixed in the phone look alike - after which
        # every window agrees with the wrong fit.
        h_held = self._h_last if self._h_last is not None else np.zeros(3)
        if n_win >= 3:
            # (Only h: holding the previous soft iron too made fresh seeds 341-370 slightly
            # worse - median +0.01 deg, one seed +0.28.)
            f_held = (Rtm_w.sum(axis=0) - S_w.sum(axis=0).T.dot(h_held)) / n_w.sum()
            w_win, spread = windows.weights(f_held, h_held, None, self._heading_mode, c)
        lam = (c.field_model_sigma / c.hard_iron_sigma) ** 2
        soft = c.soft_iron_sigma > 0 and n_win >= 3
        lam_e = (c.field_model_sigma / c.soft_iron_sigma) ** 2 if soft else 0.0
        f_lin: Array | None = self._field[0] if self._field is not None else None
        E: Array | None = None
        for _ in range(max(1, c.irls_iterations)):
            wn = w_win * n_w
            sw = float(wn.sum())
            WS = weighted_sum(w_win, S_w)  # sum w R_imu_P
            dim = 6 if f_lin is None or not soft else 12
            # (Diagonals set through a view of A's diagonal: np.eye per block costs more than
            # the solve, index arrays more than basic slices.)
            A = np.zeros((dim, dim))
            diag = A.reshape(-1)[::dim + 1]
            diag[:6] = sw
            A[:3, 3:6] = WS.T
            A[3:6, :3] = WS
            rhs = np.zeros(dim)
            rhs[:6] = w_win.dot(Rtm_m_w)
            if dim == 12:
                assert f_lin is not None  # dim 12 only with a previous f
                A_fe, A_he, A_ee, rhs_e = soft_iron_normal_equations(w_win, n_w, S_w, m_w, f_lin, 0.0)
                A[:3, 6:], A[3:6, 6:], A[6:, 6:] = A_fe, A_he, A_ee
                A[6:, :3], A[6:, 3:6] = A_fe.T, A_he.T
                rhs[6:] = rhs_e
            A_data = A.copy()  # what the samples give; the ridges and the prior follow
            diag[3:6] += sw * lam
            if dim == 12:
                diag[6:] += sw * lam_e
            wp = 0.0
            if prior is not None:
                wp = self._prior_weight(self._prior[1], c.field_model_sigma, 1.0)  # type: ignore[index]
                diag[:3] += wp
                rhs[:3] += wp * prior
            error_parts = (A, A_data, sw * lam, sw * lam_e, wp, sw / max(float(w_win.sum()), 1e-12))
            x = solve_regular(A, rhs)
            f, h = x[:3], x[3:6]
            if dim == 12:
                E = symmetric_from_params(x[6:])
            f_lin = f
            if n_win < 3:
                break
            w_win, spread = windows.weights(f, h, E, self._heading_mode, c)
            outliers = int((w_win < 0.5).sum()) / n_win
        self._h_last = h
        self._soft_iron = np.zeros((3, 3)) if E is None else E
        self._field_error = field_error_parts(*error_parts)  # once per solve, for estimate()
        if n_win >= 3:
            self._ambiguity_var = windows.ambiguity_var
            self._heading_mode = windows.heading(f)
        return f, h, spread, outliers

    def _up_estimate(self) -> Array:
        """Gravity direction in the panorama frame from the current sums (z before any)."""
        if self._n == 0:
            return np.array([0.0, 0.0, 1.0])
        g, _ = self._solve_gravity()
        norm = float(np.linalg.norm(g))
        return g / norm if norm > 0 else np.array([0.0, 0.0, 1.0])

    # -- result ----------------------------------------------------------------------------

    def _solve_geometry(self, gravity: tuple[Array, Array], field: tuple[Array, Array, float, float]
                        ) -> tuple[Array, float, float, float] | None:
        """R_pano_enu by the gravity-first construction of eq. 3-4 from one gravity and one field
        solve, with |g|, tan(dip) and the field's part of the heading variance (None when the
        field is vertical)."""
        c = self.config
        f_P, _, f_sigma, _ = field
        # The 3-vectors as Python floats (this runs at every gravity and field solve).
        g0, g1, g2 = gravity[0].tolist()
        f0, f1, f2 = f_P.tolist()
        g_norm = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
        u0, u1, u2 = g0 / g_norm, g1 / g_norm, g2 / g_norm  # up
        e0, e1, e2 = f1 * u2 - f2 * u1, f2 * u0 - f0 * u2, f0 * u1 - f1 * u0  # east = f x up
        f_h = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
        if f_h < 1e-6:
            return None
        e0, e1, e2 = e0 / f_h, e1 / f_h, e2 / f_h
        n0, n1, n2 = u1 * e2 - u2 * e1, u2 * e0 - u0 * e2, u0 * e1 - u1 * e0  # north = up x east
        R_pano_magenu = np.array([[e0, n0, u0], [e1, n1, u1], [e2, n2, u2]])
        R_pano_enu = R_pano_magenu @ rot_z(-c.declination_rad).T if c.declination_rad else R_pano_magenu
        self._field_enu_ref = R_pano_enu.T.dot(f_P)
        # A tilt error turns east = f x up by up to tilt * tan(dip): it leaks into the heading.
        tan_dip = abs(f0 * u0 + f1 * u1 + f2 * u2) / f_h
        assert self._field_error is not None  # set by every field solve
        prior_sigma = self._prior[1] if self._prior is not None else 0.0
        field_var = field_heading_mse(self._field_error, f_sigma, R_pano_magenu[:, 0], f_h, c.hard_iron_prior_sigma,
                                      c.soft_iron_prior_sigma, prior_sigma)
        return R_pano_enu, g_norm, tan_dip, field_var

    def estimate(self) -> WorldAlignmentEstimate | None:
        """The current R_pano_enu with its covariance (None before any field sample)."""
        if not self.ready:
            return None
        field = self._field
        assert field is not None  # ready
        if not self._dirty and self._estimate is not None:
            return self._estimate
        c = self.config
        gravity = self._solve_gravity()
        geometry = self._geometry
        if geometry is None or not (geometry[0][0] is gravity and geometry[0][1] is field
                                    and geometry[0][2] is c.declination_rad):
            key = (gravity, field, c.declination_rad)
            # Between solves only the session's span changes (the tilt variance): the rotation
            # and the field's part of the heading variance are computed once per solve pair.
            solved = self._solve_geometry(gravity, field)
            if solved is None:
                return self._estimate
            geometry = self._geometry = (key, *solved)
        _, R_pano_enu, g, tan_dip, field_var = geometry
        # Covariance (alignment_covariance): the hand's motion in the tilt; the windows' scatter
        # and the hard iron's bias through the field solve in the heading; plus floors.
        span_s = 0.0 if self._t_first_ns is None else (self._t_last_ns - self._t_first_ns) * 1e-9
        tilt_var = hand_tilt_variance(c.hand_velocity_m_s, c.hand_period_s, self._ramp_s, span_s, g) \
            + c.tilt_floor_rad ** 2
        heading_var = (field_var + c.heading_floor_rad ** 2
                       + tilt_var * tan_dip ** 2 + self._ambiguity_var)
        covariance = np.zeros((3, 3))  # (three item assignments cost less than an array of nine floats)
        covariance[0, 0] = covariance[1, 1] = tilt_var
        covariance[2, 2] = heading_var
        self._estimate = WorldAlignmentEstimate(
            R_pano_enu=R_pano_enu, covariance_enu=covariance,
            field_outlier_share=field[3], hard_iron=field[1], accel_bias=gravity[1], soft_iron=self._soft_iron,
            field_scale=self._field_scale)
        self._dirty = False
        return self._estimate
