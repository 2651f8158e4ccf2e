"""Two-stage map initialisation from a planar scene (Klein & Murray 2009, sec. 5.1).

Stage 1: the first frame with enough multi-scale corners (sec. 3.1) becomes the first keyframe;
its corners are un-projected to the z = 1 plane. In later frames the points are projected by a
homography ``H`` in SL(3) (normalised coordinates, first keyframe -> current), predicted with the
full-frame rotation prior (sec. 4), searched with the warped-patch search (the template warp is
the local affine of ``H``) and ``H`` is updated by robust (Tukey) Gauss-Newton on the 8 SL(3)
generators. Every frame ``H`` is decomposed (Faugeras-Lustman via ``cv2.decomposeHomographyMat``)
into hypotheses (R, t, n) with the plane n.X = 1; hypotheses that put points behind either camera
are dropped. The decomposition is *constrained* when the condition number (min/max eigenvalue)
of ``J^T J`` is large enough, J the sigma-normalised Jacobian of all measured projections w.r.t.
8-DoF changes of the decomposition (3 R, 3 t, 2 n). A pure rotation keeps H a rotation, t = 0 and
n unobservable, so it never becomes constrained: the initialiser then reports 'waiting'.

Stage 2: if two hypotheses remain, each gets its own 3-D map by triangulation against the first
keyframe and its own SE(3) pose is tracked (patch search + robust pose update with a *fixed*
Tukey scale, so objectives are comparable) until one's robustified objective is twice the
other's. The survivor, its triangulated points and the two keyframes go to
``MapMaker.initialise_map``. Scale: the initial plane is at distance 1 from the first keyframe
(n.X = 1), the map frame is the first keyframe's camera frame.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm

from .camera import Camera
from .patch_search import SearchConfig, search_points
from .pose_update import refine_pose, tukey_weight
from .pyramid import multiscale_corners
from ..rotations import so3_exp, trace_angle
from .rotation_prior import estimate_rotation
from .slam_map import Keyframe

log = logging.getLogger(__name__)

Array = NDArray[np.float64]
Image = NDArray[np.uint8]

WAIT_ROTATION_MSG = 'waiting: move the camera sideways (pure rotation cannot initialise)'

# SL(3) generators: translations, rotation, isotropic scale, aspect, shear, projective.
_GEN = np.zeros((8, 3, 3))
_GEN[0, 0, 2] = 1
_GEN[1, 1, 2] = 1
_GEN[2, 0, 1], _GEN[2, 1, 0] = -1, 1
_GEN[3] = np.diag([1.0, 1.0, -2.0])
_GEN[4] = np.diag([1.0, -1.0, 0.0])
_GEN[5, 0, 1], _GEN[5, 1, 0] = 1, 1
_GEN[6, 2, 0] = 1
_GEN[7, 2, 1] = 1


@dataclass(frozen=True)
class InitConfig:
    """Initialiser parameters (sec. 5.1)."""

    max_corners: int = 150
    min_corners: int = 40
    min_tracked: int = 20  #: fewer found points in a frame restarts initialisation
    min_tracked_fraction: float = 0.25
    #: Condition number (lambda_min / lambda_max of J^T J) at which the decomposition counts as
    #: constrained (tuned: ~4 cm sideways at 0.5 m, 50-60 deg FOV; BA refines the rest).
    condition_threshold: float = 6.0e-5
    rotation_wait_deg: float = 2.0  #: rotation from the first keyframe that flags 'pure rotation'
    translation_wait: float = 0.02  #: |t| / plane distance under which motion counts as rotation
    ratio: float = 2.0  #: stage-2 objective ratio that eliminates a hypothesis
    objective_floor: float = 2.0  #: added to both objectives before the ratio test
    max_stage2_frames: int = 15
    tukey_scale: float = 1.0  #: fixed Tukey scale (sigma units) for the hypothesis objectives
    search: SearchConfig = field(default_factory=SearchConfig)


@dataclass
class InitStatus:
    """What the initialiser did with a frame."""

    state: str  #: 'initialising' | 'waiting' | 'done' | 'lost'
    message: str
    R_c_w: Array | None = None
    t_c_w: Array | None = None
    n_measured: int = 0
    n_inliers: int = 0
    condition: float = 0.0
    #: When done: the two keyframes, points and their observations (MapMaker.initialise_map args).
    kf0: Keyframe | None = None
    kf1: Keyframe | None = None
    xyz: Array | None = None
    uv0: Array | None = None
    uv1: Array | None = None
    levels: NDArray[np.int64] | None = None


@dataclass
class _Hypothesis:
    """One decomposition (R, t, n) of H; in stage 2 also its map and its tracked pose."""

    R: Array
    t: Array
    n: Array
    #: (N, 3) points triangulated for this hypothesis (NaN where not); empty until stage 1
    #: finds the decomposition constrained and triangulates.
    xyz: Array = field(default_factory=lambda: np.zeros((0, 3)))
    #: Pose tracked in stage 2, starting from the decomposition's (R, t) (the second keyframe).
    R_cur: Array = field(init=False)
    t_cur: Array = field(init=False)
    objective: float = 0.0

    def __post_init__(self) -> None:
        self.R_cur, self.t_cur = self.R.copy(), self.t.copy()


#: What stage 1 keeps of the frame that becomes the second keyframe: pyramid, small blurry
#: image, stamp, pixels of the first keyframe's corners in it (NaN where not found), measured mask.
_SecondView = tuple[list[Image], NDArray[np.float32], int, Array, NDArray[np.bool_]]


def _proj(K: Array, Y: Array) -> Array:
    z = np.where(np.abs(Y[:, 2]) > 1e-9, Y[:, 2], 1e-9)
    return np.column_stack([K[0, 0] * Y[:, 0] / z + K[0, 2], K[1, 1] * Y[:, 1] / z + K[1, 2]])


def homography_affines(H: Array, K: Array, rays: Array) -> tuple[Array, Array]:
    """Predicted pixels (N, 2) of ``rays`` under normalised ``H`` and A = d src px / d cur px."""
    Y = rays @ H.T
    uv = _proj(K, Y)
    # d(cur px)/d(src px) = K2 dpi(Y) H K^-1 (2x2 part)
    z = Y[:, 2]
    fx, fy = K[0, 0], K[1, 1]
    Hn = H
    # d Y / d (src normalised x, y) = H[:, :2]
    dY = np.broadcast_to(Hn[:, :2], (len(rays), 3, 2))
    dpi = np.zeros((len(rays), 2, 3))
    dpi[:, 0, 0] = 1 / z
    dpi[:, 0, 2] = -Y[:, 0] / z ** 2
    dpi[:, 1, 1] = 1 / z
    dpi[:, 1, 2] = -Y[:, 1] / z ** 2
    Jn = dpi @ dY  # d cur normalised / d src normalised
    Jpx = Jn * np.array([[fx / fx, fx / fy], [fy / fx, fy / fy]])[None]
    det = Jpx[:, 0, 0] * Jpx[:, 1, 1] - Jpx[:, 0, 1] * Jpx[:, 1, 0]
    det = np.where(np.abs(det) > 1e-12, det, 1e-12)
    A = np.empty_like(Jpx)
    A[:, 0, 0] = Jpx[:, 1, 1] / det
    A[:, 1, 1] = Jpx[:, 0, 0] / det
    A[:, 0, 1] = -Jpx[:, 0, 1] / det
    A[:, 1, 0] = -Jpx[:, 1, 0] / det
    return uv, A


def refine_homography(H: Array, rays: Array, uv_meas: Array, K: Array, sigma: float,
                      iterations: int = 6) -> tuple[Array, NDArray[np.bool_]]:
    """Tukey-robust Gauss-Newton on SL(3): ``H <- expm(sum a_k G_k) H`` (sec. 5.1)."""
    H = H.copy()
    w = np.ones(len(rays))
    for _ in range(iterations):
        Y = rays @ H.T
        uv = _proj(K, Y)
        e = (uv - uv_meas) / sigma
        en = np.linalg.norm(e, axis=1)
        scale = float(np.clip(1.4826 * np.median(en), 1.0, 8.0))
        w = tukey_weight(en, 4.685 * scale)
        z = Y[:, 2]
        dpi = np.zeros((len(Y), 2, 3))
        dpi[:, 0, 0] = K[0, 0] / z
        dpi[:, 0, 2] = -K[0, 0] * Y[:, 0] / z ** 2
        dpi[:, 1, 1] = K[1, 1] / z
        dpi[:, 1, 2] = -K[1, 1] * Y[:, 1] / z ** 2
        GY = np.einsum('kij,nj->nik', _GEN, Y)  # (N, 3, 8)
        J = np.einsum('nai,nik->nak', dpi, GY) / sigma  # (N, 2, 8)
        Jw = J * w[:, None, None]
        A = np.einsum('nak,nal->kl', Jw, J) + 1e-6 * np.eye(8)
        g = np.einsum('nak,na->k', Jw, e)
        try:
            a = -np.linalg.solve(A, g)
        except np.linalg.LinAlgError:
            break
        H = expm(np.tensordot(a, _GEN, 1)) @ H
        H /= np.cbrt(np.linalg.det(H))
        if np.linalg.norm(a) < 1e-8:
            break
    return H, w > 0


def decompose(H: Array, rays: Array) -> list[_Hypothesis]:
    """Physically valid (R, t, n) of normalised ``H = R + t n^T`` (points in front of both views)."""
    n_sol, Rs, ts, ns = cv2.decomposeHomographyMat(H, np.eye(3))
    out: list[_Hypothesis] = []
    for R, t, nrm in zip(Rs, ts, ns):
        nrm = nrm.reshape(3)
        t = t.reshape(3)
        dots = rays @ nrm
        if np.mean(dots > 0) < 0.9:
            continue
        X = rays / np.where(dots > 1e-9, dots, 1e-9)[:, None]
        Xc = X @ R.T + t
        if np.mean(Xc[:, 2] > 0) < 0.9:
            continue
        # float64 in (H), float64 out; np.array copies as .copy() did.
        out.append(_Hypothesis(np.array(R, dtype=np.float64), np.array(t, dtype=np.float64),
                               np.array(nrm, dtype=np.float64)))
    return out


def decomposition_condition(hyp: _Hypothesis, rays: Array, K: Array, sigma: float) -> float:
    """lambda_min / lambda_max of J^T J, J = d projections / d (3 R, 3 t, 2 n) (sec. 5.1)."""
    def proj(R: Array, t: Array, n: Array) -> Array:
        X = rays / (rays @ n)[:, None]
        return _proj(K, X @ R.T + t).reshape(-1) / sigma
    base = proj(hyp.R, hyp.t, hyp.n)
    b1 = np.cross(hyp.n, [1.0, 0, 0] if abs(hyp.n[0]) < 0.9 else [0, 1.0, 0])
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(hyp.n, b1)
    eps = 1e-5
    cols = []
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        cols.append((proj(so3_exp(d) @ hyp.R, hyp.t, hyp.n) - base) / eps)
    for k in range(3):
        d = np.zeros(3)
        d[k] = eps
        cols.append((proj(hyp.R, hyp.t + d, hyp.n) - base) / eps)
    for b in (b1, b2):
        nn = hyp.n + eps * b
        cols.append((proj(hyp.R, hyp.t, nn / np.linalg.norm(nn)) - base) / eps)
    J = np.column_stack(cols)
    ev = np.linalg.eigvalsh(J.T @ J)
    return float(max(ev[0], 0.0) / max(ev[-1], 1e-30))


def triangulate(rays0: Array, uv1: Array, K: Array, R: Array, t: Array) -> Array:
    """Points (N, 3) in the first keyframe's frame from its rays and pixels in a view (R, t).

    Linear (DLT) two-view triangulation; points behind either camera are NaN.
    """
    P0 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P1 = np.hstack([R, t.reshape(3, 1)])
    x1 = np.column_stack([(uv1[:, 0] - K[0, 2]) / K[0, 0], (uv1[:, 1] - K[1, 2]) / K[1, 1]])
    X = cv2.triangulatePoints(P0, P1, rays0[:, :2].T.astype(np.float64), x1.T.astype(np.float64))
    X = (X[:3] / np.where(np.abs(X[3]) > 1e-12, X[3], 1e-12)).T
    bad = (X[:, 2] <= 1e-6) | ((X @ R.T + t)[:, 2] <= 1e-6) | ~np.isfinite(X).all(1)
    X[bad] = np.nan
    return X


class Initialiser:
    """Sec. 5.1 two-stage initialiser; feed it every frame with :meth:`process`."""

    def __init__(self, camera: Camera, config: InitConfig | None = None) -> None:
        self.camera = camera
        self.cfg = config or InitConfig()
        self.K = camera.K
        self._coarse_cam: Camera | None = None
        self.reset()

    def reset(self) -> None:
        self.stage = 0
        self.pyr0: list[Image] | None = None
        self.sbi0: NDArray[np.float32] | None = None
        self.stamp0 = 0
        self.uv0 = np.zeros((0, 2))
        self.rays = np.zeros((0, 3))
        self.H = np.eye(3)
        self.sbi_prev: NDArray[np.float32] | None = None
        self.hyps: list[_Hypothesis] = []
        self.kf1_data: _SecondView | None = None
        self.stage2_frames = 0

    def _first_keyframe(self) -> tuple[list[Image], NDArray[np.float32]]:
        """Pyramid and small blurry image of the first keyframe; :meth:`_start` sets both
        before stage 1, and stages 1 and 2 are the only callers."""
        assert self.pyr0 is not None and self.sbi0 is not None, 'initialiser: no first keyframe'
        return self.pyr0, self.sbi0

    # ------------------------------------------------------------------------------------------
    def _rotation(self, sbi: NDArray[np.float32], n_levels: int) -> Array:
        if self.sbi_prev is None:
            return np.eye(3)
        if self._coarse_cam is None:
            self._coarse_cam = self.camera.at_level(n_levels - 1)
        est = estimate_rotation(self.sbi_prev, sbi, self._coarse_cam, iterations=6)
        if not np.isfinite(est.residual) or est.residual > est.residual0 * 1.05 or trace_angle(est.R_cur_prev) > 0.5:
            return np.eye(3)
        return est.R_cur_prev

    def _start(self, pyr: list[Image], sbi: NDArray[np.float32], stamp_ns: int) -> InitStatus:
        uv, _ = multiscale_corners(pyr, max_corners=self.cfg.max_corners, border=12)
        if len(uv) < self.cfg.min_corners:
            return InitStatus('initialising', f'initialising: not enough texture ({len(uv)} corners)')
        self.reset()
        self.stage = 1
        self.pyr0, self.sbi0, self.stamp0 = pyr, sbi, stamp_ns
        self.uv0 = uv
        self.rays = self.camera.unproject(uv)
        self.sbi_prev = sbi
        log.info('initialiser: first keyframe with %d corners', len(uv))
        return InitStatus('initialising', 'initialising: first keyframe taken, move the camera sideways',
                          np.eye(3), np.zeros(3), len(uv), len(uv))

    def process(self, pyr: list[Image], sbi: NDArray[np.float32], stamp_ns: int) -> InitStatus:
        """One frame of initialisation; ``state == 'done'`` carries the initial map."""
        if self.stage == 0:
            return self._start(pyr, sbi, stamp_ns)
        dR = self._rotation(sbi, len(pyr))
        self.sbi_prev = sbi
        if self.stage == 1:
            return self._stage1(pyr, sbi, stamp_ns, dR)
        return self._stage2(pyr, sbi, stamp_ns, dR)

    def _search_h(self, pyr: list[Image], H: Array) -> tuple[NDArray[np.bool_], Array]:
        uv_pred, A = homography_affines(H, self.K, self.rays)
        inside = self.camera.in_image(uv_pred, 12.0)
        found = np.zeros(len(self.rays), bool)
        uv = np.full((len(self.rays), 2), np.nan)
        idx = np.nonzero(inside)[0]
        if len(idx):
            pyr0, _ = self._first_keyframe()
            res = search_points(pyr, self.camera, np.eye(3), np.zeros(3), np.zeros((len(idx), 3)),
                                {0: pyr0}, np.zeros(len(idx), np.int64), self.uv0[idx],
                                np.repeat(np.eye(3)[None], len(idx), 0), np.zeros((len(idx), 3)),
                                1, self.cfg.search, uv_pred0=uv_pred[idx], A=A[idx])
            found[idx] = res.found
            uv[idx] = res.uv0
        return found, uv

    def _stage1(self, pyr: list[Image], sbi: NDArray[np.float32], stamp_ns: int, dR: Array) -> InitStatus:
        H_pred = dR @ self.H
        found, uv = self._search_h(pyr, H_pred)
        nf = int(found.sum())
        if nf < max(self.cfg.min_tracked, self.cfg.min_tracked_fraction * len(self.rays)):
            log.info('initialiser: lost the first keyframe (%d found), restarting', nf)
            st = self._start(pyr, sbi, stamp_ns)
            st.message = 'initialising: lost track, restarted from this frame'
            return st
        H, inl = refine_homography(H_pred, self.rays[found], uv[found], self.K, 2.0)
        self.H = H
        meas = np.zeros(len(self.rays), bool)
        meas[np.nonzero(found)[0][inl]] = True
        hyps = decompose(H, self.rays[meas])
        cond = max((decomposition_condition(h, self.rays[meas], self.K, 2.0) for h in hyps), default=0.0)
        # A pose to report: the hypothesis closest to the previous one (any: same rotation at start).
        R_rep = hyps[0].R if hyps else np.eye(3)
        tnorm = max((float(np.linalg.norm(h.t)) for h in hyps), default=0.0)
        if not hyps or cond < self.cfg.condition_threshold:
            if not hyps:
                # Degenerate decomposition (no translation): the rotation is H's polar part.
                U, S, Vt = np.linalg.svd(H / np.median(np.linalg.svd(H, compute_uv=False)))
                R_rep = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
            rot_deg = float(np.degrees(trace_angle(R_rep)))
            if rot_deg > self.cfg.rotation_wait_deg and tnorm < max(self.cfg.translation_wait,
                                                                   0.15 * np.radians(rot_deg)):
                return InitStatus('waiting', WAIT_ROTATION_MSG, None, None, nf, int(meas.sum()), cond)
            return InitStatus('initialising', f'initialising: move the camera sideways (constraint {cond:.1e})',
                              None, None, nf, int(meas.sum()), cond)
        # Constrained: build one 3-D map per remaining hypothesis (stage 2).
        self.hyps = []
        for h in hyps:
            X = np.full((len(self.rays), 3), np.nan)
            X[meas] = triangulate(self.rays[meas], uv[meas], self.K, h.R, h.t)
            h.xyz = X  # h.R_cur, h.t_cur start at (h.R, h.t) (_Hypothesis.__post_init__)
            self.hyps.append(h)
        self.kf1_data = (pyr, sbi, stamp_ns, uv.copy(), meas.copy())
        log.info('initialiser: decomposition constrained (%.2e), %d hypotheses, %d points',
                 cond, len(self.hyps), int(meas.sum()))
        if len(self.hyps) == 1:
            return self._finish(self.hyps[0], nf)
        self.stage = 2
        self.stage2_frames = 0
        return InitStatus('initialising', 'initialising: two plane hypotheses, keep moving',
                          None, None, nf, int(meas.sum()), cond)

    def _stage2(self, pyr: list[Image], sbi: NDArray[np.float32], stamp_ns: int, dR: Array) -> InitStatus:
        self.stage2_frames += 1
        objs = []
        nf_all = []
        for h in self.hyps:
            ok = np.isfinite(h.xyz).all(1)
            idx = np.nonzero(ok)[0]
            R_pred, t_pred = dR @ h.R_cur, dR @ h.t_cur
            uvp, front = self.camera.project(h.xyz[idx] @ R_pred.T + t_pred)
            vis = front & self.camera.in_image(uvp, 12.0)
            idx = idx[vis]
            if len(idx) < self.cfg.min_tracked:
                objs.append(np.inf)
                nf_all.append(0)
                continue
            n = len(idx)
            res = search_points(pyr, self.camera, R_pred, t_pred, h.xyz[idx], {0: self._first_keyframe()[0]},
                                np.zeros(n, np.int64), self.uv0[idx], np.repeat(np.eye(3)[None], n, 0),
                                np.zeros((n, 3)), 1, self.cfg.search)
            f = res.found
            if f.sum() < self.cfg.min_tracked:
                objs.append(np.inf)
                nf_all.append(int(f.sum()))
                continue
            pr = refine_pose(h.xyz[idx][f], res.uv0[f], np.full(int(f.sum()), res.level), self.camera,
                             R_pred, t_pred, iterations=8, fixed_scale=self.cfg.tukey_scale)
            h.R_cur, h.t_cur = pr.R_c_w, pr.t_c_w
            # Normalise by the number searched so that different visibility does not bias.
            objs.append(pr.objective / max(1, n))
            nf_all.append(int(f.sum()))
        for h, o in zip(self.hyps, objs):
            h.objective += o if np.isfinite(o) else 1e3
        if all(not np.isfinite(o) for o in objs):
            self.reset()
            return InitStatus('initialising', 'initialising: lost track in stage 2, restarting')
        a, b = self.hyps[0].objective, self.hyps[1].objective
        fl = self.cfg.objective_floor * 0.05 * self.stage2_frames
        lo, hi = sorted([(a + fl, 0), (b + fl, 1)])
        decided = hi[0] >= self.cfg.ratio * lo[0] and self.stage2_frames >= 2
        if decided or self.stage2_frames >= self.cfg.max_stage2_frames:
            win = self.hyps[lo[1]]
            log.info('initialiser: hypothesis %d wins (objectives %.3f vs %.3f after %d frames)',
                     lo[1], a, b, self.stage2_frames)
            return self._finish(win, max(nf_all))
        return InitStatus('initialising', 'initialising: disambiguating the plane hypotheses',
                          None, None, max(nf_all), max(nf_all))

    def _finish(self, h: _Hypothesis, nf: int) -> InitStatus:
        # Stage 1 stores the second view before any hypothesis can finish.
        assert self.kf1_data is not None, 'initialiser: no second keyframe'
        pyr1, sbi1, stamp1, uv1, meas = self.kf1_data
        pyr0, sbi0 = self._first_keyframe()
        ok = meas & np.isfinite(h.xyz).all(1)
        kf0 = Keyframe(id=-1, stamp_ns=self.stamp0, R_c_w=np.eye(3), t_c_w=np.zeros(3), pyramid=pyr0,
                       sbi=sbi0, fixed=True)
        kf1 = Keyframe(id=-1, stamp_ns=stamp1, R_c_w=h.R.copy(), t_c_w=h.t.copy(), pyramid=pyr1, sbi=sbi1)
        st = InitStatus('done', 'initialised', h.R_cur.copy(), h.t_cur.copy(), nf, int(ok.sum()))
        st.kf0, st.kf1 = kf0, kf1
        st.xyz = h.xyz[ok]
        st.uv0 = self.uv0[ok]
        st.uv1 = uv1[ok]
        st.levels = np.ones(int(ok.sum()), np.int64)
        self.reset()
        return st
