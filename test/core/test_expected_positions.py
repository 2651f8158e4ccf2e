"""expected_positions (core/annotations/matching/redetector.py): the sensor prior's map positions
of the annotations (Langlotz 2011 sec. 4.2), computed for all annotations at once."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.annotations.matching import expected_positions
from ar_tracking.core.panorama.cylinder import CylinderGeometry
from ar_tracking.core.rotations import rotvec_to_matrix


def test_expected_positions_equal_the_per_annotation_projection_and_nan_without_an_orientation():
    geo = CylinderGeometry()
    rng = np.random.default_rng(4)
    dirs = rng.normal(size=(60, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    sources = [rotvec_to_matrix(rng.normal(size=3) * 0.3) for _ in range(3)]
    R_src = [None if i % 7 == 0 else sources[i % 3] for i in range(60)]
    R_tgt = rotvec_to_matrix(np.array([0.05, -0.02, 1.1]))
    got = expected_positions(dirs, R_src, R_tgt, geo)
    for i, R in enumerate(R_src):
        if R is None:
            assert np.isnan(got[i]).all()
        else:
            u, v = geo.project(R_tgt.T @ (R @ dirs[i]))
            assert got[i, 0] == float(u) and got[i, 1] == float(v)
    assert np.isnan(expected_positions(dirs[:2], [None, None], R_tgt, geo)).all()
