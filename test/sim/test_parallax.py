"""sim/camera: frames rendered from where the camera is (parallax), make-bag --parallax."""
from __future__ import annotations

import math

import cv2
import numpy as np

from ar_tracking.sim.camera import FrameRenderer, PinholeCamera
from ar_tracking.sim.model import PANO_HEIGHT, PANO_WIDTH, Lighting, Panorama

NORTH = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # camera_optical -> ENU, level, north


def _renderer() -> FrameRenderer:
    """A textured panorama whose right half of the view (azimuth 0-90 deg) is a surface 5 m
    away and the rest at infinity (sky)."""
    rng = np.random.default_rng(0)
    small = rng.random((PANO_HEIGHT // 16, PANO_WIDTH // 16, 3)).astype(np.float32)
    encoded = cv2.resize(small, (PANO_WIDTH, PANO_HEIGHT), interpolation=cv2.INTER_CUBIC)
    depth = np.full((PANO_HEIGHT, PANO_WIDTH), np.inf, np.float32)
    depth[:, :PANO_WIDTH // 4] = 5.0
    pano = Panorama(encoded=encoded, depth_m=depth, viewpoint_enu=np.zeros(3), sun_visible=False, mean_radiance=0.2)
    light = Lighting(0.0, -0.5, np.ones(3), np.ones(3), np.ones(3), np.ones(3))
    return FrameRenderer(pano, light, PinholeCamera(), np.random.default_rng(1), noise_dn=0.0)


def test_a_camera_beside_the_spot_sees_near_surfaces_move_and_the_sky_stay():
    """0.3 m east of the spot, looking north: the surface 5 m away on the right moves left by
    atan(0.3 / 5) (16.6 px at 277 px focal length), the sky on the left does not move, and no
    offset is the frame of the spot, byte for byte."""
    cam = PinholeCamera()
    R = NORTH[None]
    at_spot = _renderer().render(R, 1.0, np.ones(3))
    assert np.array_equal(_renderer().render(R, 1.0, np.ones(3), np.zeros(3)), at_spot)
    beside = _renderer().render(R, 1.0, np.ones(3), np.array([0.3, 0.0, 0.0]))
    grey = [cv2.cvtColor(f, cv2.COLOR_RGB2GRAY).astype(np.float64) for f in (at_spot, beside)]
    centre = int(round(cam.cx))
    sky = (slice(40, 200), slice(20, centre - 30))
    near = (slice(40, 200), slice(centre + 30, cam.width - 20))
    assert np.abs(grey[0][sky] - grey[1][sky]).max() <= 1.0
    (dx, dy), _ = cv2.phaseCorrelate(grey[0][near], grey[1][near])
    expected = cam.fx * math.tan(math.atan(0.3 / 5.0))
    assert abs(-dx - expected) < 1.5 and abs(dy) < 0.5, (dx, dy, expected)
