"""The panorama tracker's vectorised parts against their plain definitions: the RANSAC votes
of the closed-form two-point rotations, the template rays (camera_rays and the image projection
against their plain formulas), and the keypoint spread."""
from __future__ import annotations

import numpy as np
import pytest

from ar_tracking.core.panorama.cylinder import camera_rays, project_to_image, project_xyz
from ar_tracking.core.panorama.map import MapConfig, PanoramaMap
from ar_tracking.core.panorama.tracker import ActiveSearchTracker, pair_rotation_votes, kabsch


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_pair_rotation_votes_are_those_of_the_two_point_kabsch_rotations() -> None:
    rng = np.random.default_rng(3)
    for _ in range(20):
        R_true = _rotation(rng)
        n = 40
        b = _unit(rng.normal(size=(n, 3)) + [0, 0, 3])
        d = b @ R_true.T + rng.normal(scale=5e-4, size=(n, 3))
        d[:8] = _unit(rng.normal(size=(8, 3)))  # outliers
        d = _unit(d)
        pairs = rng.integers(0, n, size=(32, 2))
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        R_pred = _rotation(rng)
        thr = 4e-3
        votes = pair_rotation_votes(b, d, pairs, R_pred, thr)
        assert votes.shape == (pairs.shape[0] + 1, n)
        Rs = [kabsch(b[p], d[p]) for p in pairs] + [R_pred]
        expect = np.array([np.linalg.norm(b @ R.T - d, axis=1) < thr for R in Rs])
        # the same masks up to residuals within rounding of the threshold
        resid = np.array([np.linalg.norm(b @ R.T - d, axis=1) for R in Rs])
        clear = np.abs(resid - thr) > 1e-9
        np.testing.assert_array_equal(votes[clear], expect[clear])
        assert votes[:-1].sum(axis=1).max() >= 30  # an outlier-free pair finds the 32 inliers


def test_pair_rotation_votes_of_a_degenerate_pair_are_empty() -> None:
    b = _unit(np.array([[0.1, 0.0, 1.0], [0.1, 0.0, 1.0], [0.0, 0.2, 1.0]]))
    votes = pair_rotation_votes(b, b.copy(), np.array([[0, 1], [0, 2]]), np.eye(3), 1e-3)
    assert not votes[0].any()  # b0 == b1: no rotation defined
    assert votes[1].all() and votes[2].all()  # identity is exact


def _camera_rays_reference(K: np.ndarray, x: np.ndarray, y: np.ndarray, unit: bool) -> np.ndarray:
    """camera_rays as it was written before it wrote into one array: broadcast copies and a
    stack (the plain formula)."""
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    yn = (np.asarray(y, float) - cy) / fy
    xn = (np.asarray(x, float) - cx - skew * yn) / fx
    r = np.stack(np.broadcast_arrays(xn, yn, np.ones_like(xn)), axis=-1)
    return r / np.linalg.norm(r, axis=-1, keepdims=True) if unit else r


def test_template_rays_equal_camera_rays_of_the_pixel_grids() -> None:
    """The tracker's template rays (gathered from its table of the frame's pixel rays) give the
    bytes of the plain formula on the full pixel grids, also after a change of camera."""
    tracker = ActiveSearchTracker()
    xr = np.array([4, 10, 200, 311, 315])
    yr = np.array([4, 15, 100, 230, 235])
    grid = np.arange(-4.0, 5.0)
    gx, gy = np.broadcast_arrays(xr[:, None, None] + grid[None, None, :], yr[:, None, None] + grid[None, :, None])
    for K in (np.array([[300.0, 0.5, 160.2], [0.0, 310.0, 119.7], [0.0, 0.0, 1.0]]),
              np.array([[277.1, 0.0, 159.5], [0.0, 277.1, 119.5], [0.0, 0.0, 1.0]])):
        expect = _camera_rays_reference(K, gx, gy, unit=False)
        got = tracker._template_rays(K, 240, 320, xr, yr)
        assert got.shape == (5, grid.size, grid.size, 3)
        assert got.tobytes() == expect.tobytes()


@pytest.mark.parametrize('shape', [(), (7,), (5, 4)])
@pytest.mark.parametrize('unit', [True, False])
def test_camera_rays_equal_the_plain_formula(shape: tuple[int, ...], unit: bool) -> None:
    """The other callers' shapes (sub-pixel matches (n,), the synthetic scenes' pixel grids,
    a single pixel) give the same bytes as the plain formula, unit or not."""
    rng = np.random.default_rng(5)
    K = np.array([[300.0, 0.5, 160.2], [0.0, 310.0, 119.7], [0.0, 0.0, 1.0]])
    x, y = rng.uniform(0, 320, size=shape), rng.uniform(0, 240, size=shape)
    got = camera_rays(K, x, y, unit=unit)
    expect = _camera_rays_reference(K, x, y, unit)
    assert got.shape == shape + (3,)
    assert got.tobytes() == expect.tobytes()


def test_project_to_image_is_project_xyz_of_the_columns() -> None:
    rng = np.random.default_rng(6)
    K = np.array([[300.0, 0.5, 160.2], [0.0, 310.0, 119.7], [0.0, 0.0, 1.0]])
    p = rng.normal(size=(50, 3))
    p[:5, 2] = 0.0  # on the image plane's z = 0: not in front
    x, y, front = project_to_image(K, p)
    zs = np.where(p[:, 2] > 1e-6, p[:, 2], 1.0)
    xn, yn = p[:, 0] / zs, p[:, 1] / zs
    assert x.tobytes() == (K[0, 0] * xn + K[0, 1] * yn + K[0, 2]).tobytes()
    assert y.tobytes() == (K[1, 1] * yn + K[1, 2]).tobytes()
    np.testing.assert_array_equal(front, p[:, 2] > 1e-6)
    x2, y2, front2 = project_xyz(K, *(np.ascontiguousarray(p[:, k]) for k in range(3)))
    assert (x2.tobytes(), y2.tobytes(), front2.tobytes()) == (x.tobytes(), y.tobytes(), front.tobytes())


def _spread_reference(tracker: ActiveSearchTracker, idx: np.ndarray, x: np.ndarray, y: np.ndarray,
                      score: np.ndarray, w: int, h: int) -> np.ndarray:
    """Round-robin over the grid cells by strength, written as loops."""
    cfg = tracker.config
    if idx.size <= cfg.max_features:
        return idx
    cells: dict[int, list[int]] = {}
    for i in range(idx.size):
        c = min(int(y[i] * cfg.grid_rows / h), cfg.grid_rows - 1) * cfg.grid_cols \
            + min(int(x[i] * cfg.grid_cols / w), cfg.grid_cols - 1)
        cells.setdefault(c, []).append(i)
    ranked = []
    for c in sorted(cells):
        for rank, i in enumerate(sorted(cells[c], key=lambda i: -score[i])):
            ranked.append((rank, -score[i], c, i))
    pick = [i for *_, i in sorted(ranked)[:cfg.max_features]]
    return idx[np.sort(pick)]


def test_spread_picks_the_strongest_of_each_cell_in_turn() -> None:
    tracker = ActiveSearchTracker()
    rng = np.random.default_rng(5)
    for t in range(200):
        m = int(rng.integers(1, 300))
        idx = np.sort(rng.choice(5000, m, replace=False))
        x, y = rng.uniform(0, 320, m), rng.uniform(0, 240, m)
        score = rng.integers(0, 6, m).astype(float) if t % 2 else rng.uniform(0, 100, m)
        got = tracker._spread(idx, x, y, score, 320, 240)
        assert got.tolist() == _spread_reference(tracker, idx, x, y, score, 320, 240).tolist()
        assert got.size == min(m, tracker.config.max_features)


def _tone_mapped_reference(pano: PanoramaMap, bits: int) -> np.ndarray:
    """The tone mapping by boolean indexing: the range of the mapped values onto [0, 2^bits - 1]."""
    top = (1 << bits) - 1
    out = np.zeros(pano.stored.shape, np.uint16 if bits > 8 else np.uint8)
    m = pano.mapped
    vals = pano.stored[m].astype(np.float32)
    if pano.config.edr:
        lo, hi = float(vals.min()), float(vals.max())
        vals = (vals - np.float32(lo)) * np.float32(top / max(hi - lo, 1.0))
    else:
        vals = vals * np.float32(top / 255.0)
    out[m] = (np.clip(vals, 0, top) + np.float32(0.5)).astype(out.dtype)
    return out


@pytest.mark.parametrize('edr, channels', [(True, 1), (True, 3), (False, 1)])
def test_tone_mapped_stretches_the_mapped_values_and_zeroes_the_rest(edr: bool, channels: int) -> None:
    pano = PanoramaMap(MapConfig(edr=edr, channels=channels))
    rng = np.random.default_rng(1)
    assert not pano.tone_mapped(16).any()  # nothing mapped yet
    hi = 65535 if edr else 255
    pano.stored[...] = rng.integers(0, hi + 1, pano.stored.shape)
    pano.mapped[100:300, 500:900] = True
    pano.mapped[rng.integers(0, 512, 500), rng.integers(0, 2048, 500)] = True
    for bits in (8, 16):
        got = pano.tone_mapped(bits)
        assert got.tobytes() == _tone_mapped_reference(pano, bits).tobytes()
        assert not got[~pano.mapped].any()


def test_the_tracker_estimates_the_log_gain_only_for_the_gain_correction() -> None:
    """The log gain is read by the 'gain' EDR correction alone; the other modes skip it."""
    from ar_tracking.core.panorama import MapperConfig, PanoramaMapper

    assert PanoramaMapper(MapperConfig(edr_correction='gain')).tracker.config.log_gain
    for mode in ('overlap', 'offset'):
        assert not PanoramaMapper(MapperConfig(edr_correction=mode)).tracker.config.log_gain
    assert not PanoramaMapper(MapperConfig(map=MapConfig(edr=False), edr_correction='gain')).tracker.config.log_gain
