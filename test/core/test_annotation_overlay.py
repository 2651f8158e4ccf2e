"""Label projection and drawing of the AR view (Langlotz 2011 sec. 3.2, 5)."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.annotations.overlay import COLOURS_RGB, Label, draw_labels, project_labels
from ar_tracking.core.rotations import rot_y

K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])


def test_label_ahead_lands_at_the_principal_point_and_behind_is_dropped():
    ahead = Label('ahead', np.array([0.0, 0.0, 1.0]))
    behind = Label('behind', np.array([0.0, 0.0, -1.0]))
    aside = Label('aside', np.array([1.0, 0.0, 0.0]))
    placed = project_labels([ahead, behind, aside], np.eye(3), K, (240, 320))
    assert [p[0].text for p in placed] == ['ahead']
    assert np.allclose(placed[0][1:], (159.5, 119.5))
    # Turning the camera 90 degrees right (about y) brings 'aside' to the centre.
    placed = project_labels([ahead, aside], rot_y(np.pi / 2), K, (240, 320))
    assert [p[0].text for p in placed] == ['aside'] and np.allclose(placed[0][1:], (159.5, 119.5))


def test_draw_uses_status_colours_and_leaves_input_untouched():
    img = np.full((240, 320, 3), 128, np.uint8)
    labs = [Label('m', np.array([0.0, 0.0, 1.0]), 'matched'), Label('i', np.array([0.3, 0.0, 1.0]), 'inferred')]
    out = draw_labels(img, project_labels(labs, np.eye(3), K, (240, 320)))
    assert (img == 128).all()
    assert tuple(out[120, 160]) == COLOURS_RGB['matched']
    x = int(round(159.5 + 300 * 0.3))
    assert tuple(out[120, x]) == COLOURS_RGB['inferred']


def test_approximate_labels_are_drawn_grey_and_hollow():
    from ar_tracking.core.annotations.overlay import COLOURS_RGB, Label, draw_labels

    img = np.zeros((120, 160, 3), np.uint8)
    placed = draw_labels(img, [(Label('Door', np.array([0.0, 0.0, 1.0]), 'approximate'), 80.0, 60.0)])
    solid = draw_labels(img, [(Label('Door', np.array([0.0, 0.0, 1.0]), 'matched'), 80.0, 60.0)])
    grey = np.all(placed == COLOURS_RGB['approximate'], axis=2)
    assert grey.any() and not np.all(placed[60, 80] == COLOURS_RGB['approximate'])  # hollow centre
    assert np.all(solid[60, 80] == COLOURS_RGB['matched'])
    drawn = placed.sum(axis=2) > 0
    assert drawn.sum() > 50  # '~Door' and the ring
    assert np.all(placed[drawn][:, 0] == placed[drawn][:, 1])  # all of it grey


def test_with_a_lens_distortion_a_label_lands_where_the_raw_frame_shows_it():
    """Barrel distortion pulls a label near the corner toward the centre: the label goes where
    the distorted frame shows that direction - the pixel that rectification maps back onto the
    pinhole position - and a label straight ahead stays at the principal point."""
    import cv2

    D = np.array([-0.25, 0.07, 0.0, 0.0, 0.0])
    corner = Label('corner', np.array([0.45, 0.32, 1.0]) / np.linalg.norm([0.45, 0.32, 1.0]))
    ahead = Label('ahead', np.array([0.0, 0.0, 1.0]))
    pinhole = dict((lab.text, (x, y)) for lab, x, y in project_labels([corner, ahead], np.eye(3), K, (240, 320)))
    raw = dict((lab.text, (x, y)) for lab, x, y in project_labels([corner, ahead], np.eye(3), K, (240, 320), D))
    assert np.allclose(raw['ahead'], (159.5, 119.5))
    shift = np.subtract(pinhole['corner'], raw['corner'])
    assert shift[0] > 5 and shift[1] > 3, shift  # pulled toward the centre by pixels
    back = cv2.undistortPoints(np.array([[raw['corner']]]), K, D, P=K).reshape(2)
    assert np.allclose(back, pinhole['corner'], atol=0.05)
