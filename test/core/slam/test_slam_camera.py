"""Rectifier: distortion from camera_info undone so the SLAM's pinhole camera holds."""
from __future__ import annotations

import cv2
import numpy as np

from ar_tracking.core.slam.camera import Rectifier

K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])


def test_no_distortion_passes_images_through():
    r = Rectifier.from_calibration(K, np.zeros(5), 320, 240, readout_s=0.02)
    img = np.random.default_rng(0).integers(0, 255, (240, 320), dtype=np.uint8)
    assert r(img) is img
    assert (r.camera.fx, r.camera.cx, r.camera.readout_s) == (300.0, 159.5, 0.02)


def test_distorted_dot_lands_where_the_pinhole_camera_projects_it():
    D = np.array([-0.25, 0.07, 0.0, 0.0])
    r = Rectifier.from_calibration(K, D, 320, 240)
    X = np.array([[0.2, -0.1, 1.0]])
    uv_dist = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, D)[0].reshape(2)
    img = np.zeros((240, 320), np.uint8)
    cv2.circle(img, (int(round(uv_dist[0] * 8)), int(round(uv_dist[1] * 8))), 16, 255, -1, cv2.LINE_AA, shift=3)
    out = r(img).astype(float)
    v, u = np.mgrid[:240, :320]
    centroid = np.array([(out * u).sum(), (out * v).sum()]) / out.sum()
    uv_pin, _ = r.camera.project(X)
    assert np.linalg.norm(centroid - uv_pin[0]) < 0.5
    assert np.linalg.norm(uv_dist - uv_pin[0]) > 3  # the distortion was worth undoing
