"""Marker map and the camera pose from all corners of all visible markers (Caarls 2009 sec.
2.4: "in case more markers are seen at the same time, and their geometric relation is known, our
pose estimation will use all available detected points in a more precise estimation").

The pose is solved with OpenCV (SQPnP for several markers, IPPE_SQUARE for one, then
Levenberg-Marquardt refinement) on the *undistorted* refined corners, then a few Gauss-Newton
steps weighted by each corner's own 1-sigma (:attr:`MarkerObservation.corner_sigma_px`: larger
for blurred, poorly fitted or partly occluded sides) where the detector gives one. Its
covariance is the weighted Gauss-Newton one, (J^T W J)^-1 with W = diag(1 / sigma_i^2), each
sigma_i at least the configured corner noise, scaled up by the reprojection residuals when they
are larger than the sigmas say (chi^2 per degree of freedom > 1), propagated to the camera pose
in the map frame. Few corners, blur and occlusion therefore all show in the covariance.

Marker frame (OpenCV's): x right, y up, z out of the marker towards the viewer; the corners are
(-s/2, s/2), (s/2, s/2), (s/2, -s/2), (-s/2, -s/2) - the ArUco corner order.

Covariance layout (ROS PoseWithCovariance): x, y, z, then rotation about the map's x, y, z axes
(a small rotation applied on the left: R_true = exp([dtheta]x) R_est).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from . import MarkerError
from ..rotations import matrix_to_rotvec, quat_xyzw_to_matrix
from .detection import MarkerObservation

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MapMarker:
    id: int
    size_m: float
    position: Array          # centre in the map frame, m
    R_map_marker: Array      # marker frame -> map frame

    def corners_map(self) -> Array:
        h = self.size_m / 2
        local = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
        return self.position + local @ self.R_map_marker.T


@dataclass(frozen=True)
class MarkerMap:
    frame_id: str
    markers: dict[int, MapMarker]

    @property
    def ids(self) -> set[int]:
        return set(self.markers)

    @staticmethod
    def from_arrays(ids: Sequence[int], sizes_m: Sequence[float], poses: Sequence[float],
                    frame_id: str = 'enu') -> 'MarkerMap':
        """From flat arrays: ids, sizes (m), poses (7 per marker: x, y, z, qx, qy, qz, qw)."""
        ids, sizes, poses = list(ids), list(sizes_m), list(poses)
        if len(sizes) != len(ids) or len(poses) != 7 * len(ids):
            raise MarkerError(f'marker map: {len(ids)} ids need {len(ids)} sizes and {7 * len(ids)} pose values '
                              f'(got {len(sizes)} and {len(poses)})')
        markers = {}
        for i, mid in enumerate(ids):
            p = np.asarray(poses[7 * i:7 * i + 7], dtype=float)
            size = float(sizes[i])
            q = p[3:]
            if not np.all(np.isfinite(p)) or not size > 0 or abs(np.linalg.norm(q) - 1) > 1e-3:
                raise MarkerError(f'marker {mid}: size must be > 0 and the pose finite with a unit quaternion')
            if int(mid) in markers:
                raise MarkerError(f'marker {mid} appears twice in the map')
            markers[int(mid)] = MapMarker(int(mid), size, p[:3], quat_xyzw_to_matrix(q))
        return MarkerMap(frame_id, markers)

    @staticmethod
    def from_yaml(path: str | Path) -> 'MarkerMap':
        """A marker-map file: {frame_id, markers: [{id, size_m, position: [x, y, z],
        orientation_xyzw: [x, y, z, w]}]}."""
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise MarkerError(f'{path}: cannot read the marker map ({exc})') from exc
        return MarkerMap.from_text(text, str(path))

    @staticmethod
    def from_text(text: str, what: str = 'marker map') -> 'MarkerMap':
        """The same document as :meth:`from_yaml`, given as YAML (or JSON) text."""
        try:
            doc: Any = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise MarkerError(f'{what}: not YAML ({str(exc).splitlines()[0]})') from exc
        path = what
        if not isinstance(doc, dict) or not isinstance(doc.get('markers'), list):
            raise MarkerError(f'{path}: a marker map needs a "markers" list')
        ids, sizes, poses = [], [], []
        for m in doc['markers']:
            try:
                ids.append(int(m['id']))
                sizes.append(float(m['size_m']))
                poses += [float(v) for v in m['position']] + [float(v) for v in m.get('orientation_xyzw', [0, 0, 0, 1])]
            except (KeyError, TypeError, ValueError) as exc:
                raise MarkerError(f'{path}: bad marker entry {m!r}') from exc
        return MarkerMap.from_arrays(ids, sizes, poses, str(doc.get('frame_id', 'enu')))


@dataclass(frozen=True)
class CameraPoseEstimate:
    R_map_cam: Array
    p_map_cam: Array
    cov: Array               # 6x6, ROS order (see module docstring)
    rms_px: float
    n_points: int
    ids: tuple[int, ...]


def _camera_from_rt(rvec: Array, tvec: Array) -> tuple[Array, Array]:
    R, _ = cv2.Rodrigues(rvec)
    R_cam_map = np.asarray(R, dtype=np.float64)
    return R_cam_map.T, -R_cam_map.T @ np.asarray(tvec, dtype=np.float64).reshape(3)


#: chi-square 99.9 % quantile for 8 degrees of freedom (one marker's four corners): a marker
#: whose corners miss the pose of the others by more than this (in their own sigmas) is left out.
CHI2_8DOF_999 = 26.12


def estimate_camera_pose(observations: Sequence[MarkerObservation], marker_map: MarkerMap,
                         focal_px: float, corner_sigma_px: float = 0.1,
                         marker_gate_chi2: float = CHI2_8DOF_999) -> CameraPoseEstimate | None:
    """Camera pose in the map frame from every corner of every mapped marker; None when no
    mapped marker is visible or the solution is not finite.

    With three or more markers, one whose corners do not fit the pose of the others - its
    squared reprojection residuals, in its corners' own sigmas, above ``marker_gate_chi2``
    (8 degrees of freedom) times the others' median chi-square per 8 when that is above 1 - is
    left out and the pose solved again, one marker at a time as long as three remain after it
    (with three, two markers cannot outvote one reliably: in blurred pan frames that dropped
    good markers; 0 disables it). Why: a marker partly hidden by an occluder as
    dark as its border gives a side line that follows the occluder's edge where it covers the
    border (the detector's quad already bends there); its corners are then off by half a pixel
    with sigmas that claim a tenth of that, enough to move a 4-marker pose by 0.3-0.4 cm,
    always the same way while the camera looks past the occluder. The others tell."""
    est = _solve_pose(observations, marker_map, focal_px, corner_sigma_px)
    while est is not None and marker_gate_chi2 > 0 and len(est[1]) >= 4:
        pose, chi2 = est
        worst = max(chi2, key=lambda k: chi2[k])
        # judged against the others: when every marker misses by more than its sigmas say
        # (sigmas too small for this camera), that is no reason to drop one of them
        others = float(np.median([v for k, v in chi2.items() if k != worst]))
        if chi2[worst] <= marker_gate_chi2 * max(1.0, others / 8.0):
            break
        keep = [o for o in observations if o.id != worst and o.id in chi2]
        retry = _solve_pose(keep, marker_map, focal_px, corner_sigma_px)
        if retry is None:
            break
        est = retry
    return None if est is None else est[0]


def _solve_pose(observations: Sequence[MarkerObservation], marker_map: MarkerMap, focal_px: float,
                corner_sigma_px: float) -> tuple[CameraPoseEstimate, dict[int, float]] | None:
    """The weighted pose of :func:`estimate_camera_pose` and each marker's chi-square."""
    obj, img, ids, sig = [], [], [], []
    for o in observations:
        m = marker_map.markers.get(o.id)
        if m is None:
            continue
        obj.append(m.corners_map())
        img.append(o.corners_norm * focal_px)
        ids.append(o.id)
        s_i = getattr(o, 'corner_sigma_px', None)
        s_i = np.full(4, corner_sigma_px) if s_i is None else np.maximum(np.asarray(s_i, float).reshape(4), corner_sigma_px)
        sig.append(np.where(np.isfinite(s_i), s_i, 1e3))
    if not obj:
        return None
    X = np.concatenate(obj).astype(np.float64)
    x = np.concatenate(img).astype(np.float64)
    w = 1.0 / np.repeat(np.concatenate(sig), 2) ** 2   # one weight per image coordinate
    K = np.array([[focal_px, 0, 0], [0, focal_px, 0], [0, 0, 1.0]])
    if len(ids) == 1:
        m = marker_map.markers[ids[0]]
        h = m.size_m / 2
        local = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
        n, rvecs, tvecs, errs = cv2.solvePnPGeneric(local, x, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if n == 0:
            return None
        best = int(np.argmin(np.asarray(errs).ravel()))
        R_cm, _ = cv2.Rodrigues(rvecs[best])
        R_cam_map = np.asarray(R_cm, dtype=np.float64) @ m.R_map_marker.T
        t = tvecs[best].reshape(3) - R_cam_map @ m.position
        r0, _ = cv2.Rodrigues(R_cam_map)
        rvec0, tvec0 = np.asarray(r0, dtype=np.float64), t.reshape(3, 1)
    else:
        ok, r0, t0 = cv2.solvePnP(X, x, K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            return None
        rvec0, tvec0 = np.asarray(r0, dtype=np.float64), np.asarray(t0, dtype=np.float64)
    rvec_lm, tvec_lm = cv2.solvePnPRefineLM(X, x, K, None, rvec0.copy(), tvec0.copy(),
                                            (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 1e-12))
    rvec = np.asarray(rvec_lm, dtype=np.float64).reshape(3, 1)
    tvec = np.asarray(tvec_lm, dtype=np.float64).reshape(3, 1)
    for _ in range(3):  # weighted Gauss-Newton: the corners count by their own sigma
        proj, J = cv2.projectPoints(X, rvec, tvec, K, None)
        res = (proj.reshape(-1, 2) - x).ravel()
        J6 = J[:, :6]
        H = J6.T @ (J6 * w[:, None])
        try:
            step = -np.linalg.solve(H, J6.T @ (w * res))
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(step)):
            return None
        rvec, tvec = rvec + step[:3, None], tvec + step[3:, None]
        if np.abs(step).max() < 1e-12:
            break
    proj, J = cv2.projectPoints(X, rvec, tvec, K, None)
    res = proj.reshape(-1, 2) - x
    J6 = J[:, :6]
    chi2_dof = float(np.sum(w * res.ravel() ** 2) / max(res.size - 6, 1))
    try:
        cov_rt = max(1.0, chi2_dof) * np.linalg.inv(J6.T @ (J6 * w[:, None]))
    except np.linalg.LinAlgError:
        return None
    R_map_cam, p_map_cam = _camera_from_rt(rvec, tvec)
    # Propagate to (p, dtheta) of the camera in the map frame by a numeric Jacobian.
    F = np.zeros((6, 6))
    params = np.concatenate([rvec.ravel(), tvec.ravel()])
    for i in range(6):
        e = 1e-6
        dp = params.copy()
        dp[i] += e
        R2, p2 = _camera_from_rt(dp[:3], dp[3:])
        F[:3, i] = (p2 - p_map_cam) / e
        F[3:, i] = matrix_to_rotvec(R2 @ R_map_cam.T) / e
    cov = F @ cov_rt @ F.T
    cov = 0.5 * (cov + cov.T)
    if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(R_map_cam)) and np.all(np.isfinite(p_map_cam))):
        return None
    r2 = (w * res.ravel() ** 2).reshape(-1, 8).sum(axis=1)   # per marker (4 corners x 2)
    chi2 = {mid: float(v) for mid, v in zip(ids, r2)}
    return CameraPoseEstimate(R_map_cam, p_map_cam, cov, float(np.sqrt(np.mean(np.sum(res ** 2, 1)))),
                              len(X), tuple(ids)), chi2
