"""Horizontal parallax between the authoring and the browsing standing point (an extension of
Langlotz 2011 sec. 4.3 for the 2 m radius of sec. 6.1).

The global alignment of sec. 4.3 is a rotation; the two panoramas are never taken from the same
spot. Let ``(e1, e2, up)`` be right-handed, ``h(theta) = cos(theta) e1 + sin(theta) e2`` the
horizontal direction at azimuth ``theta`` and ``t = t1 e1 + t2 e2`` the horizontal displacement of
the browsing spot from the authoring spot. An anchor at horizontal distance ``d`` then appears
turned about ``up`` by

    delta(theta) ~= (t1 sin(theta) - t2 cos(theta)) / d = a cos(theta) + b sin(theta)

(small-angle; ``a = -t2 / d``, ``b = t1 / d``), and the spot is nearer to it by ``t . h``: its
horizontal distance becomes ``d (1 - q)`` with

    q(theta) = (t1 cos(theta) + t2 sin(theta)) / d = b cos(theta) - a sin(theta),

the quadrature of the same sinusoid (no new parameter), so ``tan(elevation)`` grows by
``1 / (1 - q) ~ 1 + q`` (``ParallaxModel.elevation``). Near eye level that is nothing, but a window
5 m up a facade 15 m away rises by 0.6 deg when the spot is 0.5 m nearer. The depths are not in
the annotation record, so the model takes one common depth: after the rotation, the heading
residuals of the matched annotations follow ``c + a cos(theta) + b sin(theta)``, with ``c`` what
the rotation left of the heading. Fitted by least squares with a Gaussian prior on ``(a, b)``
(``sigma_parallax``: about 1 m at 50 m), it moves the inferred annotations - whose placement
otherwise carries the mean parallax the rotation absorbed from the matched ones - and the
positions around which candidates are chosen.

The common depth is fitted mostly on landmarks (:mod:`.landmarks`), nearer on the whole than the
facades the annotations are on; :func:`fit_depth_scale` gives the annotations' parallax as a
factor of the model's from the matched annotations (``MatchConfig.parallax_scale_sigma``), so an
inferred label is not moved as far as a tree in front of it would be.

Azimuths are measured about ``up`` (the browsing panorama's vertical from gravity), so the model
applies after the gravity-constrained alignment (``MatchConfig.gravity_alignment``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..rotations import cross3, rotations_about_axis
from ..window_statistics import median

Array = NDArray[np.float64]


def _horizontal_axes(up: Array) -> tuple[Array, Array]:
    """Two unit vectors completing ``up`` to a right-handed frame (e1, e2, up)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    # cross3: the same products as np.cross, without its ~10 us of overhead per call.
    e1 = cross3(up, helper)
    e1 /= np.linalg.norm(e1)
    return e1, cross3(up, e1)


def _elevation_factor(up: Array, dirs: Array) -> Array:
    """(n,) ``sin(el) cos(el)`` of (n, 3) directions about ``up``: the change of elevation per
    unit of the relative change of ``tan(elevation)``."""
    dirs = np.asarray(dirs, float).reshape(-1, 3)
    sin_el = np.clip(dirs @ up / np.linalg.norm(dirs, axis=1), -1.0, 1.0)
    return np.asarray(sin_el * np.sqrt(1.0 - sin_el ** 2), float)


def _regressors(theta: Array) -> Array:
    """(n, 3) columns of the model's heading shift ``c + a cos + b sin`` at azimuths ``theta``."""
    return np.stack([np.ones_like(theta), np.cos(theta), np.sin(theta)], axis=1)


@dataclass(frozen=True)
class ParallaxModel:
    """Heading shift ``c + a cos(theta) + b sin(theta)`` (rad) about ``up``; theta from ``e1``."""

    up: Array
    c: float
    a: float
    b: float
    #: Whether :meth:`apply` changes the elevations too (the radial part of the displacement).
    elevation: bool = False

    def azimuth(self, dirs: Array) -> Array:
        """(n,) azimuths (rad) about ``up`` of (n, 3) directions, from ``e1`` towards ``e2``."""
        e1, e2 = _horizontal_axes(self.up)
        dirs = np.asarray(dirs, float).reshape(-1, 3)
        return np.arctan2(dirs @ e2, dirs @ e1)

    def shift(self, dirs: Array, th: Array | None = None) -> Array:
        """(n,) heading shifts (rad) at the given directions (``th``: their azimuths, if known)."""
        th = self.azimuth(dirs) if th is None else th
        return self.c + self.a * np.cos(th) + self.b * np.sin(th)

    def radial(self, dirs: Array, th: Array | None = None) -> Array:
        """(n,) the displacement towards the anchors over their depth, ``q = b cos - a sin``: the
        quadrature of the heading sinusoid (module docstring; ``th`` as in :meth:`shift`)."""
        th = self.azimuth(dirs) if th is None else th
        return self.b * np.cos(th) - self.a * np.sin(th)

    def elevation_shift(self, dirs: Array, th: Array | None = None) -> Array:
        """(n,) change of elevation (rad, small-angle) :meth:`apply` makes at the directions: 0
        without ``elevation``, else ``sin(el) cos(el) q`` (``th`` as in :meth:`shift`)."""
        dirs = np.asarray(dirs, float).reshape(-1, 3)
        if not self.elevation:
            return np.zeros(len(dirs))
        return _elevation_factor(self.up, dirs) * self.radial(dirs, th)

    def apply(self, dirs: Array) -> Array:
        """(n, 3) directions turned about ``up`` by their shift, and with ``elevation`` raised or
        lowered by the radial displacement."""
        dirs = np.asarray(dirs, float).reshape(-1, 3)
        th = self.azimuth(dirs)
        out = np.einsum('nij,nj->ni', rotations_about_axis(self.up, self.shift(dirs, th)), dirs)
        if not self.elevation:
            return out
        # tan(elevation) scales with d / d' (module docstring): the vertical component by 1 + q.
        out = out + np.outer((out @ self.up) * self.radial(dirs, th), self.up)
        return out / np.linalg.norm(out, axis=1, keepdims=True)

    def scaled(self, scale: float) -> ParallaxModel:
        """The same heading ``c`` with the parallax ``(a, b)`` times ``scale`` (a depth ratio:
        anchors ``1 / scale`` times as far as the matches the model was fitted on)."""
        return ParallaxModel(self.up, self.c, scale * self.a, scale * self.b, self.elevation)

    @property
    def amplitude(self) -> float:
        """|t| / d of the fit (rad)."""
        return math.hypot(self.a, self.b)


def fit_parallax(predicted: Array, observed: Array, up: Array, sigma_match: float = 0.01,
                 sigma_parallax: float = 0.02, trim_sigmas: float = 0.0, elevation: bool = False) -> ParallaxModel:
    """The model from (n, 3) directions where the rotation puts the matches (``predicted``) and
    where they were found (``observed``), n >= 1: weighted least squares of the heading
    residuals (``sigma_match``: a match's localisation plus the depth differences the common
    depth ignores), ``a`` and ``b`` pulled to 0 with ``sigma_parallax``; ``c`` free.

    ``trim_sigmas`` > 0: one refit without the matches whose residual exceeds that many robust
    standard deviations (1.4826 x median absolute residual; never less than sigma_match / 5) of
    the first fit. Among the landmarks of a panorama (:mod:`.landmarks`) some are much nearer
    than the anchors - trees, poles - and turn two or three times as far: outliers of the common
    depth, which would otherwise set the amplitude for the far anchors. ``elevation``: the model
    also moves elevations (:attr:`ParallaxModel.elevation`; fitted on the headings alone)."""
    k = np.asarray(up, float) / np.linalg.norm(up)
    model = ParallaxModel(k, 0.0, 0.0, 0.0)
    th = model.azimuth(predicted)
    r = (model.azimuth(observed) - th + math.pi) % (2 * math.pi) - math.pi
    X = _regressors(th)
    prior = np.diag([0.0, 1.0, 1.0])[1:] / sigma_parallax
    keep = np.ones(th.size, bool)
    for _ in range(2 if trim_sigmas > 0 else 1):
        A = np.vstack([X[keep] / sigma_match, prior])
        y = np.concatenate([r[keep] / sigma_match, [0.0, 0.0]])
        coef = np.linalg.lstsq(A, y, rcond=None)[0]
        res = np.abs(r - X @ coef)
        keep = res <= max(trim_sigmas * 1.4826 * median(res), sigma_match / 5)
    c, a, b = coef
    return ParallaxModel(k, float(c), float(a), float(b), elevation)


def heading_residuals(model: ParallaxModel, predicted: Array, observed: Array) -> Array:
    """(n,) heading residuals (rad, wrapped) of matches left by ``model``: observed azimuth
    minus the predicted azimuth minus the model's shift there."""
    th = model.azimuth(predicted)
    r = (model.azimuth(observed) - th + math.pi) % (2 * math.pi) - math.pi
    return np.asarray((r - model.shift(predicted) + math.pi) % (2 * math.pi) - math.pi, float)


def fit_depth_scale(model: ParallaxModel, predicted: Array, observed: Array, sigma_match: float = 0.01,
                    sigma_scale: float = 0.5, bounds: tuple[float, float] = (0.0, 2.0)) -> float:
    """The factor on the parallax of ``model`` that fits a subset of its matches best (``predicted``
    where the rotation puts them, ``observed`` where they were found; n >= 0): least squares of
    their heading residuals over the model's parallax term ``a cos + b sin`` at them, pulled to 1
    with ``sigma_scale`` (``sigma_match`` rad per residual), clipped to ``bounds``.

    The model is fitted mostly on landmarks, among which trees, poles and near corners pull the
    common depth nearer than the facades the annotations are on: on the development spots the
    anchors' parallax is ~0.75 of the model's (0.2-1.7). The matched annotations of a spot tell
    that ratio for its inferred ones, which have no match of their own."""
    p = model.shift(predicted) - model.c
    r = heading_residuals(model, predicted, observed)
    w = 1.0 / sigma_match ** 2
    s = 1.0 + float(w * (r @ p)) / (w * float(p @ p) + 1.0 / sigma_scale ** 2)
    return float(np.clip(s, *bounds))


def depth_scale_sigma(model: ParallaxModel, predicted: Array, sigma_match: float = 0.01,
                      sigma_scale: float = 0.5) -> float:
    """Standard deviation of :func:`fit_depth_scale`'s factor fitted on matches at ``predicted``
    (n >= 0): the posterior of the same linear least squares, ``sigma_scale`` with no match. A
    match where the model's parallax term is small says little about the factor."""
    p = model.shift(predicted) - model.c
    return float(1.0 / math.sqrt(float(p @ p) / sigma_match ** 2 + 1.0 / sigma_scale ** 2))


def prediction_sigma(model: ParallaxModel, predicted: Array, observed: Array, at: Array,
                     sigma_match: float = 0.01, sigma_parallax: float = 0.02) -> Array:
    """(m,) standard deviation (rad) of the model's heading shift at the (m, 3) directions ``at``:
    the posterior covariance of ``(c, a, b)`` in :func:`fit_parallax`'s least squares on the
    matches (``predicted`` / ``observed``), with their robust residual scale (1.4826 x median
    absolute, at least ``sigma_match``) for the per-match sigma. Matches bunched in one sector
    of the panorama pin the sinusoid there only: far from them it is extrapolated. With
    :attr:`ParallaxModel.elevation` the elevation change's variance at ``at`` is added."""
    X = _regressors(model.azimuth(predicted))
    r = heading_residuals(model, predicted, observed)
    s = max(sigma_match, 1.4826 * float(np.median(np.abs(r)))) if r.size else sigma_match
    info = X.T @ X / s ** 2 + np.diag([0.0, 1.0, 1.0]) / sigma_parallax ** 2
    cov = np.linalg.pinv(info)
    th = model.azimuth(at)
    Xa = _regressors(th)
    var = np.einsum('ni,ij,nj->n', Xa, cov, Xa)
    if model.elevation:  # d(elevation_shift)/d(c, a, b) = sin cos (0, -sin th, cos th)
        Xv = _elevation_factor(model.up, at)[:, None] * np.stack([np.zeros_like(th), -np.sin(th), np.cos(th)], axis=1)
        var = var + np.einsum('ni,ij,nj->n', Xv, cov, Xv)
    return np.sqrt(np.maximum(var, 0.0))


def leave_one_out_predictions(predicted: Array, observed: Array, up: Array, sigma_match: float = 0.01,
                              sigma_parallax: float = 0.02, trim_sigmas: float = 0.0, elevation: bool = False,
                              scale_rows: NDArray[np.bool_] | None = None, sigma_scale: float = 0.5,
                              bounds: tuple[float, float] = (0.0, 2.0)) -> Array:
    """(m, 3) each match's ``predicted`` direction moved by the model fitted on the other m - 1
    matches (:func:`fit_parallax` with the same arguments); a row in ``scale_rows`` by that model
    scaled by :func:`fit_depth_scale` on the other rows of ``scale_rows`` (the annotations among
    the matches; None: no scaling). A look-alike match must not pull the prediction it is judged
    against towards itself.

    The m fits are one batched solve of the normal equations of :func:`fit_parallax`'s weighted
    least squares (its rows are 3 unknowns; ~20 fits per ``result`` call of the matcher cost
    ~18 ms one by one), so the coefficients agree with it to rounding (1e-15 rad), not bit for bit."""
    pred = np.asarray(predicted, float).reshape(-1, 3)
    obs = np.asarray(observed, float).reshape(-1, 3)
    m = len(pred)
    k = np.asarray(up, float) / np.linalg.norm(up)
    base = ParallaxModel(k, 0.0, 0.0, 0.0)
    th = base.azimuth(pred)
    r = (base.azimuth(obs) - th + math.pi) % (2 * math.pi) - math.pi
    X = _regressors(th)
    prior = np.diag([0.0, 1.0, 1.0]) / sigma_parallax ** 2
    others = ~np.eye(m, dtype=bool)

    def solve(keep: NDArray[np.bool_]) -> Array:
        w = keep / sigma_match ** 2
        N = np.einsum('rj,ja,jb->rab', w, X, X) + prior
        rhs = np.einsum('rj,ja->ra', w * r[None, :], X)
        try:
            return np.asarray(np.linalg.solve(N, rhs[:, :, None])[:, :, 0], float)
        except np.linalg.LinAlgError:  # no row left in a fit: the minimum-norm solution, as lstsq's
            return np.einsum('rab,rb->ra', np.linalg.pinv(N), rhs)

    coef = solve(others)
    if trim_sigmas > 0 and m > 1:
        res = np.abs(r[None, :] - coef @ X.T)
        rest = np.sort(np.where(others, res, np.inf), axis=1)[:, :m - 1]  # each fit's own rows
        med = np.median(rest, axis=1)
        thr = np.maximum(trim_sigmas * 1.4826 * med, sigma_match / 5)
        coef = solve((res <= thr[:, None]) & others)
    c, a, b = coef[:, 0], coef[:, 1], coef[:, 2]
    cos, sin = np.cos(th), np.sin(th)
    if scale_rows is not None:
        rows = others & np.asarray(scale_rows, bool)[None, :]
        shift = c[:, None] + a[:, None] * cos + b[:, None] * sin  # each fit's at every match
        p = shift - c[:, None]  # its parallax term, as fit_depth_scale takes it
        rr = (r[None, :] - shift + math.pi) % (2 * math.pi) - math.pi
        w = 1.0 / sigma_match ** 2
        s = 1.0 + w * (rows * rr * p).sum(axis=1) / (w * (rows * p * p).sum(axis=1) + 1.0 / sigma_scale ** 2)
        s = np.where(np.asarray(scale_rows, bool), np.clip(s, *bounds), 1.0)
        a, b = s * a, s * b
    out = np.einsum('nij,nj->ni', rotations_about_axis(k, c + a * cos + b * sin), pred)
    if not elevation:
        return np.asarray(out, float)
    out = out + np.outer((out @ k) * (b * cos - a * sin), k)
    return np.asarray(out / np.linalg.norm(out, axis=1, keepdims=True), float)
