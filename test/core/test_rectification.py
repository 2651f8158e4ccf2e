"""core/rectification: a calibrated lens distortion undone (plumb_bob and equidistant)."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from ar_tracking.core.rectification import Rectification, RectificationError, check_distortion

K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])
SIZE = (320, 240)  # width, height


def _texture(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.random((30, 40)).astype(np.float32)
    return (cv2.resize(small, SIZE, interpolation=cv2.INTER_CUBIC).clip(0, 1) * 255).astype(np.uint8)


def _distorted(pinhole: np.ndarray, Kn: np.ndarray, D: np.ndarray, model: str) -> np.ndarray:
    """What the real lens (K, D) shows of a scene that the pinhole camera Kn sees as ``pinhole``:
    each distorted pixel samples the pinhole image where its ray lands."""
    yy, xx = np.mgrid[0:SIZE[1], 0:SIZE[0]].astype(np.float64)
    pts = np.stack([xx.ravel(), yy.ravel()], -1).reshape(-1, 1, 2)
    if model == 'equidistant':
        rays = cv2.fisheye.undistortPoints(pts, K, D).reshape(-1, 2)
    else:
        rays = cv2.undistortPoints(pts, K, D).reshape(-1, 2)
    u = (Kn[0, 0] * rays[:, 0] + Kn[0, 2]).reshape(SIZE[1], SIZE[0]).astype(np.float32)
    v = (Kn[1, 1] * rays[:, 1] + Kn[1, 2]).reshape(SIZE[1], SIZE[0]).astype(np.float32)
    return cv2.remap(pinhole, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


@pytest.mark.parametrize('model, D', [('plumb_bob', [-0.28, 0.08, 0.0002, -0.0001, 0.0]),
                                      ('rational_polynomial', [-0.2, 0.05, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0]),
                                      ('equidistant', [-0.02, 0.01, -0.005, 0.001])])
def test_a_distorted_frame_is_rectified_to_its_pinhole_image(model, D):
    """The rectified image of a distorted frame is the pinhole image the new K sees (NCC > 0.98
    inside a 10 px border), and a grey frame and a colour frame are remapped alike."""
    D = np.asarray(D)
    rect = Rectification.from_calibration(K, D, *SIZE, model)
    assert not rect.identity and rect.K[2, 2] == 1.0
    pinhole = _texture()
    frame = _distorted(pinhole, rect.K, D, model)
    back = rect(frame)
    a, b = back[10:-10, 10:-10].astype(float), pinhole[10:-10, 10:-10].astype(float)
    assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.98
    assert np.corrcoef(frame[10:-10, 10:-10].astype(float).ravel(), b.ravel())[0, 1] < 0.95  # it was distorted
    colour = rect(np.dstack([frame] * 3))
    assert colour.shape == (SIZE[1], SIZE[0], 3) and np.array_equal(colour[..., 1], back)


def test_no_distortion_passes_frames_through():
    rect = Rectification.from_calibration(K, np.zeros(5), *SIZE)
    frame = _texture(1)
    assert rect.identity and rect(frame) is frame and np.array_equal(rect.K, K)


@pytest.mark.parametrize('D, model, message', [([np.nan, 0, 0, 0, 0], 'plumb_bob', 'not finite'),
                                               ([0.1, 0.0, 0.0], 'plumb_bob', '3 distortion coefficients'),
                                               ([0.1, 0.0, 0.0, 0.0, 0.0], 'equidistant', 'needs 4')])
def test_coefficients_it_cannot_use_are_one_clear_error(D, model, message):
    with pytest.raises(RectificationError, match=message):
        check_distortion(D, model)


def test_the_cache_builds_a_rectification_once_per_calibration():
    from ar_tracking.core.rectification import RectificationCache

    cache = RectificationCache()
    D = np.array([-0.2, 0.05, 0.0, 0.0, 0.0])
    first, built = cache.get(K, D, *SIZE)
    again, built_again = cache.get(K.copy(), list(D), *SIZE)  # equal values: the same one
    assert built and not built_again and again is first
    other, built_other = cache.get(K, D * 0.5, *SIZE)
    assert built_other and other is not first
