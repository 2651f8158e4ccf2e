"""The IMU input between two samples when the angular acceleration steps inside the interval.

The time update of Fig. 7 takes the mean of the two samples at the ends of a step as the input
over it (trapezoid). That is exact while the rates change linearly between samples, but a tool
that starts or stops turning quickly steps its angular acceleration alpha (the torque changes
faster than the 10 ms between samples), and an IMU mounted at a lever arm r from the point the
tool turns about feels that step at once as a step of alpha x r in its specific force (4 m/s^2
for 70 rad/s^2 at 6 cm). The trapezoid then puts the step at mid-interval: wrong by up to
half an interval times the step, a velocity error of up to 2 cm/s per pan start or stop,
i.e. ~1 cm of position half a second later - the largest error source left in the fused
position of the quick pans (a noise-free 100 Hz integration drifts 0.9 cm over one pan,
0.05 cm at 1 kHz).

The gyro tells *where* in the interval the step happened: the angular rate is continuous and
kinks there. With the slopes before (samples k-2, k-1) and after (k, k+1) the interval
(k-1, k), the rate change over the interval, w_k - w_k-1 = alpha_b tau + alpha_a (dt - tau),
gives the kink time tau. Where the rate kinks, the specific force steps: it is modelled as
following its own trend before tau (from a_k-2, a_k-1) and after tau (from a_k, a_k+1), which
is exact for the step of alpha x r and for anything linear on either side. The model needs the
sample after the interval: until it arrives an interval is integrated as a trapezoid, and the
roll-back integrates it again when that sample finds a kink there (without one the model is the
same trapezoid, so the first integration stands).

The rate itself keeps the straight line between its samples: it is continuous at the kink, so
the trapezoid's error there is second order (alpha-step dt^2 / 8, ~0.05 deg per pan start),
and inside a pan, where the rate curves smoothly, the straight line is the better of the two
models (lines continued from the neighbouring intervals overshoot a smooth curve: measured, the
kinked rate made the fused orientation worse, 0.034 -> 0.045 deg, for no gain in position).

A kink counts when the change of slope stands out of the gyro's white noise (``kink_sigmas``
times the noise of a second difference, sqrt(6) sigma_z,w / dt); otherwise the trapezoid is
kept (it is exact for a straight line, and the noise would only move tau at random).
"""
from __future__ import annotations

import math
from dataclasses import dataclass


from .eskf import Array

#: A slope change this many noise sigmas above the gyro noise is a kink.
KINK_SIGMAS = 6.0


@dataclass(frozen=True)
class IntervalModel:
    """Piecewise-linear gyro rate and specific force over one IMU interval [0, dt] (s): one
    line each before and after the kink time ``tau`` (tau None: one straight line, the
    trapezoid)."""

    dt: float
    w0: Array           # rate at the interval's start (sample k-1)
    w1: Array           # rate at its end (sample k)
    a0: Array
    a1: Array
    tau: float | None = None
    jerk_before: Array | None = None
    jerk_after: Array | None = None

    def means(self, u0: float, u1: float) -> tuple[Array, Array]:
        """Mean rate (the straight line between the samples) and mean specific force (stepped
        at the kink) over [u0, u1], seconds from the interval's start."""
        return (_mean(u0, u1, self.dt, self.w0, self.w1, None, None, None),
                _mean(u0, u1, self.dt, self.a0, self.a1, self.tau, self.jerk_before, self.jerk_after))


def interval_model(dt: float, w: tuple[Array | None, Array, Array, Array | None],
                   a: tuple[Array | None, Array, Array, Array | None], gyro_noise_rad_s: float,
                   kink_sigmas: float = KINK_SIGMAS) -> IntervalModel:
    """The model of the interval between samples k-1 and k from the samples k-2 .. k+1 (``w``
    and ``a`` as (k-2, k-1, k, k+1), the outer ones None when not there: then the trapezoid).
    Samples are assumed equally spaced by ``dt`` (the IMU's own rate)."""
    wm2, w0, w1, wp1 = w
    am2, a0, a1, ap1 = a
    if wm2 is None or wp1 is None or am2 is None or ap1 is None or dt <= 0:
        return IntervalModel(dt, w0, w1, a0, a1)
    alpha_b = (w0 - wm2) / dt
    alpha_a = (wp1 - w1) / dt
    d_alpha = alpha_b - alpha_a
    noise = math.sqrt(6.0) * gyro_noise_rad_s / dt
    n2 = float(d_alpha @ d_alpha)
    if n2 < (kink_sigmas * noise) ** 2:
        return IntervalModel(dt, w0, w1, a0, a1)
    # w1 - w0 = alpha_b tau + alpha_a (dt - tau)  ->  tau (least squares over the axes)
    tau = float(d_alpha @ (w1 - w0 - alpha_a * dt)) / n2
    tau = min(max(tau, 0.0), dt)
    return IntervalModel(dt, w0, w1, a0, a1, tau, (a0 - am2) / dt, (ap1 - a1) / dt)


def _piecewise(u: float, dt: float, y0: Array, y1: Array, tau: float | None,
               s_before: Array | None, s_after: Array | None) -> Array:
    if tau is None or s_before is None or s_after is None:
        return y0 + (y1 - y0) * (u / dt if dt > 0 else 0.0)
    return y0 + s_before * u if u <= tau else y1 - s_after * (dt - u)


def _mean(u0: float, u1: float, dt: float, y0: Array, y1: Array, tau: float | None,
          s_before: Array | None, s_after: Array | None) -> Array:
    """Mean of the piecewise-linear signal over [u0, u1] (exact: each piece is a line)."""
    if u1 <= u0:
        return _piecewise(u0, dt, y0, y1, tau, s_before, s_after)
    if tau is None or not (u0 < tau < u1):
        # one line over [u0, u1]: its mean is its value at the middle
        return _piecewise(0.5 * (u0 + u1), dt, y0, y1, tau, s_before, s_after)
    left = _piecewise(0.5 * (u0 + tau), dt, y0, y1, tau, s_before, s_after)
    right = _piecewise(0.5 * (tau + u1), dt, y0, y1, tau, s_before, s_after)
    return (left * (tau - u0) + right * (u1 - tau)) / (u1 - u0)
