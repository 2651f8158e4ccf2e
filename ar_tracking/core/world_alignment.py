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
from .alignment_covariance import FieldErrorParts, field_error_parts, field_heading_mse, hand_tilt_variance
from .rotations import cross3, rot_z
from .soft_iron import soft_iron_normal_equations, symmetric_from_params
from .window_statistics import WindowSums, cauchy_about_median, shorth
from .world_alignment_config import WorldAlignmentConfig

__all__ = ['WorldAlignment', 'WorldAlignmentConfig', 'WorldAlignmentEstimate']

Array = NDArray[np.float64]


@dataclass(frozen=True)
class WorldAlignmentEstimate:
    """R_pano_enu (rotates ENU vectors into the panorama frame) and its uncertainty."""

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
        self._prev_omega: Array | None = None
        self._prev_accel: Array | None = None
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
        self._field: tuple[Array, Array, float, float] | None = None  # f_P, h (relative), sigma, outliers
        self._prior = prior
        self._h_last: Array | None = None
        self._soft_iron = np.zeros((3, 3))
        self._field_scale = 1.0
        self._ambiguity_var = 0.0
        self._heading_mode: float | None = None
        self._field_enu_ref: Array | None = None if prior is None else getattr(self, '_field_enu_ref', None)
        self._estimate: WorldAlignmentEstimate | None = None
        self._dirty = True

    # -- samples ---------------------------------------------------------------------------

    def add(self, t_ns: int, R_pano_imu: Array, accel: Array, mag: Array | None = None,
            omega: Array | None = None) -> None:
        """One calibrated IMU sample (specific force, m/s^2; field, any unit; rate, rad/s, for
        the lever-arm model) with the IMU's orientation in the panorama frame at its stamp."""
        t_ns = int(t_ns)
        R_imu_P = R_pano_imu.T
        self._n += 1
        if self._t_first_ns is None:
            self._t_first_ns = t_ns
        self._t_last_ns = t_ns
        gw = self._gw
        k = gw.open(t_ns)
        gw.n[k] += 1
        sums = gw.sums
        sums['S'][k] += R_imu_P
        sums['Rta'][k] += R_pano_imu @ accel
        sums['a'][k] += accel
        if omega is not None and self._lever:
            self._add_lever_arm(t_ns, R_pano_imu, omega, accel, k)
        aa = float(accel @ accel)
        self._sum_aa += aa
        self._sum_a_norm += math.sqrt(aa)
        self._dirty = True
        if mag is not None:
            self.add_field(t_ns, R_pano_imu, mag)

    def add_field(self, t_ns: int, R_pano_imu: Array, mag: Array) -> None:
        """One calibrated field sample (any unit) with the IMU's orientation in the panorama
        frame at its own stamp (a magnetometer has its own rate and stamps)."""
        t_ns, R_imu_P, fw = int(t_ns), R_pano_imu.T, self._fw
        self._dirty = True
        k = fw.open(t_ns)
        fw.n[k] += 1
        fw.sums['S'][k] += R_imu_P
        fw.sums['Rtm'][k] += R_pano_imu @ mag
        fw.sums['m'][k] += mag
        fw.sums['norm'][k] += math.sqrt(float(mag @ mag))
        self._field_samples += 1
        span_ns = t_ns - (t_ns if self._t_first_ns is None else self._t_first_ns)
        period_ns = min(int(self.config.solve_period_s * 1e9), max(100_000_000, int(self.config.solve_period_share * span_ns)))
        if self._solve_t_ns is None or t_ns - self._solve_t_ns >= period_ns \
                or self._field_samples < 8:
            self._solve_t_ns = t_ns
            self._field = self._solve_field()

    def _add_lever_arm(self, t_ns: int, R_pano_imu: Array, omega: Array, accel: Array, k: int) -> None:
        """Sums of the lever-arm terms: a phone turning about a centre at r (IMU frame) feels
        alpha x r + omega x (omega x r) = K r. The person's turn, not the wrist's tremor, carries
        the phone around that centre, so rate and specific force are low-passed alike
        (``lever_arm_tau_s``) and alpha is the difference of the low-passed rate."""
        c = self.config
        prev_t = self._prev_omega_t_ns
        if self._prev_omega is None or not 0 < t_ns - prev_t < 100_000_000:
            self._prev_omega, self._prev_accel, self._prev_omega_t_ns = omega, accel, t_ns
            return
        dt = (t_ns - prev_t) * 1e-9
        gain = min(1.0, dt / c.lever_arm_tau_s)
        w_prev, a_prev = self._prev_omega, self._prev_accel
        assert a_prev is not None  # set together with the rate
        w_lp = w_prev + gain * (omega - w_prev)
        a_lp = a_prev + gain * (accel - a_prev)
        self._prev_omega, self._prev_accel, self._prev_omega_t_ns = w_lp, a_lp, t_ns
        self._lever_count += 1
        if self._lever_count % 2:
            return  # every other sample, counted twice: the orbit is slow next to the rate
        ax, ay, az = (w_lp - w_prev) / dt
        wx, wy, wz = w_lp
        ww = wx * wx + wy * wy + wz * wz
        # K = [alpha]x + [omega]x^2 = [alpha]x + omega omega^T - |omega|^2 I, times 2.
        K = 2.0 * np.array([[wx * wx - ww, wx * wy - az, wx * wz + ay],
                            [wy * wx + az, wy * wy - ww, wy * wz - ax],
                            [wz * wx - ay, wz * wy + ax, wz * wz - ww]])
        sums = self._gw.sums
        sums['RtK'][k] += R_pano_imu @ K
        sums['K'][k] += K
        sums['KtK'][k] += 0.5 * (K.T @ K)
        sums['Kta'][k] += K.T @ a_lp

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
        c = self.config
        n_w, sums = self._gw.arrays()
        S_w, Rta_w, a_w = sums['S'], sums['Rta'], sums['a']
        k = len(n_w)
        ramp = max(1.0, min(k / 2.0, c.gravity_ramp_s / c.window_s))
        self._ramp_s = ramp * c.window_s
        idx = np.arange(k) + 0.5
        w = np.minimum(1.0, np.minimum(idx, k - idx) / ramp)
        n = float(w @ n_w)
        sum_R = np.einsum('k,kij->ij', w, S_w)
        sum_Rta = w @ Rta_w
        sum_a = w @ a_w
        g_mag = self._sum_a_norm / self._n
        # Per-sample noise of the model, for the ridge weight: the scatter of |a| about g.
        var = max(self._accel_var, 0.05 ** 2)
        lam_b = var / c.accel_bias_sigma_m_s2 ** 2
        lever = c.lever_arm_sigma_m > 0
        dim = 9 if lever else 6
        A = np.zeros((dim, dim))
        A[:3, :3] = np.eye(3) * n
        A[:3, 3:6] = sum_R.T
        A[3:6, :3] = sum_R
        A[3:6, 3:6] = np.eye(3) * (n + lam_b)
        rhs = np.zeros(dim)
        rhs[:3], rhs[3:6] = sum_Rta, sum_a
        if lever:
            RtK = np.einsum('k,kij->ij', w, sums['RtK'])
            K = np.einsum('k,kij->ij', w, sums['K'])
            A[:3, 6:] = RtK
            A[6:, :3] = RtK.T
            A[3:6, 6:] = K
            A[6:, 3:6] = K.T
            A[6:, 6:] = np.einsum('k,kij->ij', w, sums['KtK']) + np.eye(3) * (var / c.lever_arm_sigma_m ** 2)
            rhs[6:] = w @ sums['Kta']
        if self._prior is not None:
            R_pe, sigma = self._prior
            wp = self._prior_weight(sigma, math.sqrt(var), g_mag)
            A[:3, :3] += np.eye(3) * wp
            rhs[:3] += wp * (R_pe @ np.array([0.0, 0.0, g_mag]))
        x = np.asarray(np.linalg.solve(A, rhs), dtype=np.float64)
        g, b = x[:3], x[3:6]
        if lever:
            self._lever_arm = x[6:]
        self._gravity = (g, b)
        self._gravity_windows = closed
        n = float(self._n)
        # Per-axis residual variance of a - R g - b from the sums (the hand's acceleration and
        # the sensor noise): it weighs the ridge of the next solve and sets the covariance.
        all_R, all_Rta, all_a = S_w.sum(axis=0), Rta_w.sum(axis=0), a_w.sum(axis=0)
        sq = (self._sum_aa - 2.0 * g @ all_Rta - 2.0 * b @ all_a + n * (g @ g)
              + 2.0 * g @ (all_R.T @ b) + n * (b @ b))
        self._accel_var = max(sq / (3.0 * n), 0.0)
        return g, b

    def _solve_field(self) -> tuple[Array, Array, float, float]:
        """Robust fit of m = (I + E) R_imu_P f_P + h (ridges on h and E), over windows of ``window_s``.

        A disturbance lasts seconds and turns the field for all of its samples at once, so the
        samples are grouped in short windows (``window_s``): each window gives the heading
        of the field it implies in the panorama frame, the windows' headings are compared with
        the cluster :meth:`_choose_cluster` takes as the Earth's field, and a window
        that departs gets a Cauchy weight for all its samples (this survives up to half of the
        windows disturbed; a per-sample loss started from least squares does not, once a long
        disturbance has pulled the fit). f_P and h are
        then refitted by weighted least squares (E linearised about the previous f_P, see
        :mod:`.soft_iron`). The normal equations are sums, so only the
        windows' sums are kept. Returns f_P, h (relative to |B|), the residual sigma of the
        window headings (rad) and the share of windows weighted below one half."""
        c = self.config
        n_w, sums = self._fw.arrays()
        S_w, Rtm_w, m_w, norm_w = sums['S'], sums['Rtm'], sums['m'], sums['norm']
        scale = float(np.median(norm_w / n_w))
        if scale <= 0 or not math.isfinite(scale):
            scale = 1.0
        self._field_scale = scale
        Rtm_w = Rtm_w / scale
        m_w = m_w / scale
        n_win = len(n_w)
        w_win = np.ones(n_win)
        prior = None
        if self._prior is not None and self._field_enu_ref is not None:
            prior = self._prior[0] @ self._field_enu_ref
        up = self._up_estimate()
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
            f_held = (Rtm_w.sum(axis=0) - np.einsum('nji,j->i', S_w, h_held)) / n_w.sum()
            w_win, spread = self._window_weights(n_w, S_w, Rtm_w, f_held, h_held, up, None)
        lam = (c.field_model_sigma / c.hard_iron_sigma) ** 2
        soft = c.soft_iron_sigma > 0 and n_win >= 3
        lam_e = (c.field_model_sigma / c.soft_iron_sigma) ** 2 if soft else 0.0
        f_lin: Array | None = self._field[0] if self._field is not None else None
        E: Array | None = None
        for _ in range(max(1, c.irls_iterations)):
            wn = w_win * n_w
            sw = float(wn.sum())
            WS = np.einsum('n,nij->ij', w_win, S_w)  # sum w R_imu_P
            dim = 6 if f_lin is None or not soft else 12
            A = np.zeros((dim, dim))
            A[:3, :3] = np.eye(3) * sw
            A[:3, 3:6] = WS.T
            A[3:6, :3] = WS
            A[3:6, 3:6] = np.eye(3) * sw
            rhs = np.zeros(dim)
            rhs[:3], rhs[3:6] = w_win @ Rtm_w, w_win @ m_w
            if dim == 12:
                assert f_lin is not None  # dim 12 only with a previous f
                A_fe, A_he, A_ee, rhs_e = soft_iron_normal_equations(w_win, n_w, S_w, m_w, f_lin, 0.0)
                A[:3, 6:], A[3:6, 6:], A[6:, 6:] = A_fe, A_he, A_ee
                A[6:, :3], A[6:, 3:6] = A_fe.T, A_he.T
                rhs[6:] = rhs_e
            A_data = A.copy()  # what the samples give; the ridges and the prior follow
            A[3:6, 3:6] += np.eye(3) * sw * lam
            if dim == 12:
                A[6:, 6:] += np.eye(6) * sw * lam_e
            wp = 0.0
            if prior is not None:
                wp = self._prior_weight(self._prior[1], c.field_model_sigma, 1.0)  # type: ignore[index]
                A[:3, :3] += np.eye(3) * wp
                rhs[:3] += wp * prior
            error_parts = (A, A_data, sw * lam, sw * lam_e, wp, sw / max(float(w_win.sum()), 1e-12))
            x = np.asarray(np.linalg.solve(A, rhs), dtype=np.float64)
            f, h = x[:3], x[3:6]
            if dim == 12:
                E = symmetric_from_params(x[6:])
            f_lin = f
            if n_win < 3:
                break
            w_win, spread = self._window_weights(n_w, S_w, Rtm_w, f, h, up, E)
            outliers = float(np.mean(w_win < 0.5))
        self._h_last = h
        self._soft_iron = np.zeros((3, 3)) if E is None else E
        self._field_error = field_error_parts(*error_parts)  # once per solve, for estimate()
        if n_win >= 3:
            e1 = np.array([1.0, 0.0, 0.0]) - up[0] * up
            if float(e1 @ e1) < 1e-6:
                e1 = np.array([0.0, 1.0, 0.0]) - up[1] * up
            e1 /= float(np.linalg.norm(e1))
            self._heading_mode = math.atan2(float(f @ cross3(up, e1)), float(f @ e1))
        return f, h, spread, outliers

    def _window_weights(self, n_w: Array, S_w: Array, Rtm_w: Array, f: Array, h: Array,
                        up: Array, E: Array | None) -> tuple[Array, float]:
        """Cauchy weights of the windows (heading, strength and dip of the field each implies
        in the panorama frame, about their medians) and the heading spread (rad). ``E``: the
        residual soft iron of the fit being judged (None: not modelled)."""
        c = self.config
        mean_f = (Rtm_w - np.einsum('nji,j->ni', S_w, h)) / n_w[:, None]  # mean R_P_imu (m - h)
        if E is not None:
            S_mean = S_w / n_w[:, None, None]
            mean_f -= np.einsum('nji,jk,nkl,l->ni', S_mean, E, S_mean, f)
        # Headings about up in a basis fixed in the panorama frame, relative to f's.
        e1 = np.array([1.0, 0.0, 0.0]) - up[0] * up
        if float(e1 @ e1) < 1e-6:
            e1 = np.array([0.0, 1.0, 0.0]) - up[1] * up
        e1 /= float(np.linalg.norm(e1))
        e2 = cross3(up, e1)
        f_abs = math.atan2(float(f @ e2), float(f @ e1))
        rel = (np.arctan2(mean_f @ e2, mean_f @ e1) - f_abs + math.pi) % (2.0 * math.pi) - math.pi
        centre, spread = shorth(rel, c.cluster_share)
        spread = max(spread, math.radians(0.25))
        width = c.cauchy_scale * spread
        centre = self._choose_cluster(rel, centre, f_abs, width)
        w_psi = 1.0 / (1.0 + ((rel - centre) / width) ** 2)
        # Past reject_widths the weight is zero, not a Cauchy tail: a tail still lets the hard
        # iron drift towards a disturbance, which then looks like the clean field (with little
        # rotation a field offset fixed in the phone and one fixed in the world look alike).
        w_psi[np.abs(rel - centre) > c.reject_widths * width] = 0.0
        # Most real disturbances also change the field's strength or dip: a window whose mean
        # field departs in either is down-weighted too (a turn that keeps both is left to the
        # heading test).
        norm = np.linalg.norm(mean_f, axis=1)
        dip = np.arcsin(np.clip(-(mean_f @ up) / np.maximum(norm, 1e-12), -1.0, 1.0))
        w_norm, _ = cauchy_about_median(norm, 0.005, c.cauchy_scale)
        w_dip, _ = cauchy_about_median(dip, math.radians(0.25), c.cauchy_scale)
        return w_psi * w_norm * w_dip, spread

    def _episode_cost(self, rel: Array, centre: float, width: float) -> float:
        """Negative log-odds (nats, up to a constant) that the field whose window headings sit at
        ``centre`` is the Earth's: every other window is then disturbed, each maximal run of
        them (in time order) is one episode costing ``disturbance_onset_nats``, and every
        disturbed second costs 1 / ``disturbance_duration_s`` (episodes of exponentially
        distributed length). Runs shorter than ``min_episode_windows`` are noise: length only."""
        c = self.config
        off = np.abs(rel - centre) > c.reject_widths * width
        n_off = int(off.sum())
        if n_off == 0:
            return 0.0
        edges = np.flatnonzero(np.diff(np.concatenate(([0], off.astype(np.int8), [0]))))
        lengths = edges[1::2] - edges[0::2]
        episodes = int(np.sum(lengths >= c.min_episode_windows))
        return episodes * c.disturbance_onset_nats + n_off * c.window_s / c.disturbance_duration_s

    def _choose_cluster(self, rel: Array, densest: float, f_abs: float, width: float) -> float:
        """The heading (relative to f_abs) of the window cluster taken as the Earth's field.

        Nothing in one window tells a field turned by a disturbance (strength and dip kept)
        from the Earth's; the history does. Candidates: the densest cluster, the one the last
        solve chose and the densest of the windows far from those; the one with the lowest
        :meth:`_episode_cost` wins, the last choice keeping its place unless beaten by
        ``mode_switch_nats``. So a disturbance as long as the clean data so far takes over (the
        longer run is the likelier field), but a field the phone returns to after an episode is
        the Earth's at once (calling it disturbed would take two episodes). The doubt between
        the winner and the runner-up enters the heading variance (:attr:`_ambiguity_var`)."""
        c = self.config
        candidates = [densest]
        prev = None
        if self._heading_mode is not None:
            prev = (self._heading_mode - f_abs + math.pi) % (2.0 * math.pi) - math.pi
            candidates.append(prev)
        far = np.ones(len(rel), dtype=bool)
        for x in candidates:
            far &= np.abs(rel - x) > c.reject_widths * width
        if int(far.sum()) >= 2:
            candidates.append(shorth(rel[far])[0])
        # A candidate no window supports any more (the last choice, after h moved) cannot win.
        costs = [self._episode_cost(rel, x, width) if np.any(np.abs(rel - x) <= c.reject_widths * width)
                 else math.inf for x in candidates]
        best = int(np.argmin(costs))
        if prev is not None and math.isfinite(costs[1]) and costs[best] > costs[1] - c.mode_switch_nats:
            best = 1
        chosen, cost = candidates[best], costs[best]
        # The runner-up: the cheapest candidate clearly apart from the chosen one.
        rivals = [(k, x) for k, x in zip(costs, candidates) if abs(x - chosen) > c.reject_widths * width]
        self._ambiguity_var = 0.0
        if rivals:
            k, x = min(rivals)
            p = 1.0 / (1.0 + math.exp(min(k - cost, 50.0)))
            self._ambiguity_var = p * (1.0 - p) * (x - chosen) ** 2
        return chosen

    def _up_estimate(self) -> Array:
        """Gravity direction in the panorama frame from the current sums (z before any)."""
        if self._n == 0:
            return np.array([0.0, 0.0, 1.0])
        g, _ = self._solve_gravity()
        norm = float(np.linalg.norm(g))
        return g / norm if norm > 0 else np.array([0.0, 0.0, 1.0])

    # -- result ----------------------------------------------------------------------------

    def estimate(self) -> WorldAlignmentEstimate | None:
        """The current R_pano_enu with its covariance (None before any field sample)."""
        if not self.ready:
            return None
        if not self._dirty and self._estimate is not None:
            return self._estimate
        c = self.config
        g_P, b_a = self._solve_gravity()
        f_P, h, f_sigma, outliers = self._field  # type: ignore[misc]
        up = g_P / np.linalg.norm(g_P)
        east = cross3(f_P, up)
        f_h = float(np.linalg.norm(east))
        if f_h < 1e-6:
            return self._estimate
        east /= f_h
        north = cross3(up, east)
        R_pano_magenu = np.column_stack([east, north, up])
        R_pano_enu = R_pano_magenu @ rot_z(-c.declination_rad).T if c.declination_rad else R_pano_magenu
        self._field_enu_ref = R_pano_enu.T @ f_P
        # Covariance (alignment_covariance): the hand's motion in the tilt; the windows' scatter
        # and the hard iron's bias through the field solve in the heading; plus floors.
        span_s = 0.0 if self._t_first_ns is None else (self._t_last_ns - self._t_first_ns) * 1e-9
        g = float(np.linalg.norm(g_P))
        tilt_var = hand_tilt_variance(c.hand_velocity_m_s, c.hand_period_s, self._ramp_s, span_s, g) \
            + c.tilt_floor_rad ** 2
        # A tilt error turns east = f x up by up to tilt * tan(dip): it leaks into the heading.
        tan_dip = abs(float(f_P @ up)) / f_h
        assert self._field_error is not None  # set by every field solve
        prior_sigma = self._prior[1] if self._prior is not None else 0.0
        field_var = field_heading_mse(self._field_error, f_sigma, east, f_h, c.hard_iron_prior_sigma,
                                      c.soft_iron_prior_sigma, prior_sigma)
        heading_var = (field_var + c.heading_floor_rad ** 2
                       + tilt_var * tan_dip ** 2 + self._ambiguity_var)
        self._estimate = WorldAlignmentEstimate(
            R_pano_enu=R_pano_enu, covariance_enu=np.diag([tilt_var, tilt_var, heading_var]),
            field_outlier_share=outliers,
            hard_iron=h, accel_bias=b_a, soft_iron=self._soft_iron, field_scale=self._field_scale)
        self._dirty = False
        return self._estimate
