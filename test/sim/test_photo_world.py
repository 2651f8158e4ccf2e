"""sim/photo_world: a turn of photos laid into the simulator's panorama (the other renderer)."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_tracking.sim import photo_world
from ar_tracking.sim.bagmaker import SimError, make_bag
from ar_tracking.sim.model import PANO_HEIGHT, PANO_WIDTH
from ar_tracking.sim.photo_world import PhotoWorldError, photo_panorama

from conftest import SHARED_DATA

FOCAL_PX = 300.0
SIZE = (240, 320)  # rows, cols of each photo (hfov 56 deg)


def _texture(seed: int) -> np.ndarray:
    """An equirectangular 'scene' with detail at several scales (gamma-encoded, 0..1)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((PANO_HEIGHT // 4, PANO_WIDTH // 4, 3), np.float32)
    for scale, amp in ((3, 0.35), (9, 0.35), (31, 0.3)):
        noise = rng.random((out.shape[0] // scale + 2, out.shape[1] // scale + 2, 3)).astype(np.float32)
        out += amp * cv2.resize(noise, (out.shape[1], out.shape[0]), interpolation=cv2.INTER_CUBIC)
    return np.clip(cv2.resize(out, (PANO_WIDTH, PANO_HEIGHT), interpolation=cv2.INTER_LINEAR), 0, 1)


def _view(pano: np.ndarray, R_enu_cam: np.ndarray) -> np.ndarray:
    """A pinhole photo (SIZE, FOCAL_PX) of an equirectangular map at one orientation."""
    h, w = SIZE
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(x - (w - 1) / 2) / FOCAL_PX, (y - (h - 1) / 2) / FOCAL_PX, np.ones_like(x)], -1)
    d = rays @ R_enu_cam.T
    az = np.arctan2(d[..., 0], d[..., 1]) % (2 * math.pi)
    el = np.arcsin(d[..., 2] / np.linalg.norm(d, axis=-1))
    u = (az * PANO_WIDTH / (2 * math.pi) - 0.5).astype(np.float32)
    v = ((math.pi / 2 - el) * PANO_HEIGHT / math.pi - 0.5).astype(np.float32)
    return cv2.remap(pano, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)


def _camera(az: float, pitch: float, roll: float) -> np.ndarray:
    """camera_optical -> ENU: optical axis at compass azimuth az, pitched up, rolled."""
    s, c = math.sin(az), math.cos(az)
    level = np.array([[c, 0.0, s], [-s, 0.0, c], [0.0, -1.0, 0.0]])
    cp, sp = math.cos(pitch), math.sin(pitch)
    up = np.array([[1.0, 0.0, 0.0], [0.0, cp, sp], [0.0, -sp, cp]])  # about camera x
    cr, sr = math.cos(roll), math.sin(roll)
    about_z = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return level @ up @ about_z


def _write_turn(folder: Path, source: np.ndarray, az0: float, pitch_deg: float, roll_deg: float
                ) -> list[np.ndarray]:
    """12 JPEG photos of ``source`` 30 deg apart from azimuth az0 (hand-held: uniform pitch and
    roll within the given bounds) and their pano.txt; returns their true orientations."""
    rng = np.random.default_rng(5)
    lines, truths = [], []
    for i in range(12):
        R = _camera(az0 + math.radians(30.0 * i), math.radians(rng.uniform(-pitch_deg, pitch_deg)),
                    math.radians(rng.uniform(-roll_deg, roll_deg)))
        img = (np.clip(_view(source, R), 0, 1) * 255).astype(np.uint8)
        cv2.imwrite(str(folder / f'turn{i:02d}.jpg'), cv2.cvtColor(img, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_JPEG_QUALITY, 95])
        lines.append(f'C:\\photos\\turn{i:02d}.jpg {FOCAL_PX:.3f}')
        truths.append(R)
    (folder / 'pano.txt').write_text('\r\n'.join(lines) + '\r\n')
    return truths


@pytest.fixture(scope='module')
def turn(tmp_path_factory) -> tuple[Path, np.ndarray, float]:
    """A level turn (only the roll wanders, +-2 deg), the source map, the first azimuth."""
    folder = tmp_path_factory.mktemp('turn')
    source = _texture(3)
    az0 = math.radians(37.0)
    _write_turn(folder, source, az0, 0.0, 2.0)
    return folder, source, az0


def test_a_turn_of_photos_is_laid_where_it_was_taken(turn):
    """The laid map is the source scene turned by the first photo's azimuth (the map puts that
    photo at azimuth 0): in the band the photos cover, the two agree to a fraction of a map
    pixel (0.09 deg) and in content."""
    folder, source, az0 = turn
    laid = photo_panorama(str(folder)).encoded
    shift = int(round(math.degrees(az0) / 360 * PANO_WIDTH))
    expected = np.roll(source, -shift, axis=1)
    band = slice(PANO_HEIGHT // 2 - 150, PANO_HEIGHT // 2 + 150)  # +-13 deg of elevation
    a = cv2.cvtColor(laid[band], cv2.COLOR_RGB2GRAY).astype(np.float64)
    b = cv2.cvtColor(expected[band], cv2.COLOR_RGB2GRAY).astype(np.float64)
    (du, dv), response = cv2.phaseCorrelate(a, b)
    assert abs(du) < 1.0 and abs(dv) < 1.0 and response > 0.3, (du, dv, response)
    ncc = np.corrcoef(a.ravel(), b.ravel())[0, 1]
    assert ncc > 0.95, ncc
    # Above and below the photos: no holes, and no detail (a fade into the band's mean).
    assert np.all(laid.max(axis=2) > 0)
    top = cv2.cvtColor(laid[200:300], cv2.COLOR_RGB2GRAY)
    assert float(np.abs(np.diff(top, axis=1)).mean()) < 0.2 * float(np.abs(np.diff(a, axis=1)).mean())


def test_hand_held_photos_are_turned_into_each_other_exactly(tmp_path):
    """Pitch and roll wander by +-2 deg: each photo's rotation relative to its neighbour is found
    to 0.05 deg; the turn's axis (the mean of an unlevelled hand) is up to a degree off."""
    truths = _write_turn(tmp_path, _texture(4), 0.3, 2.0, 2.0)
    rotations = photo_world.photo_rotations(*photo_world.read_sequence(tmp_path))
    for i in range(12):
        j = (i + 1) % 12
        err = (truths[i].T @ truths[j]).T @ (rotations[i].T @ rotations[j])
        angle = math.degrees(math.acos(np.clip((np.trace(err) - 1) / 2, -1, 1)))
        assert angle < 0.05, (i, angle)
    up = np.mean([R.T @ np.array([0.0, 0.0, 1.0]) for R in rotations], axis=0)
    true_up = np.mean([R.T @ np.array([0.0, 0.0, 1.0]) for R in truths], axis=0)
    cos = up @ true_up / np.linalg.norm(up) / np.linalg.norm(true_up)
    assert math.degrees(math.acos(min(1.0, cos))) < 1.0


def test_the_first_photo_goes_to_the_azimuth_asked_for(turn):
    folder, _source, _az0 = turn
    at0 = photo_panorama(str(folder)).encoded
    at90 = photo_panorama(str(folder), 90.0).encoded
    assert np.array_equal(np.roll(at0, PANO_WIDTH // 4, axis=1), at90)


def test_a_folder_that_is_no_turn_is_one_clear_error(tmp_path, turn):
    with pytest.raises(PhotoWorldError, match='not a folder'):
        photo_world.read_sequence(tmp_path / 'missing')
    with pytest.raises(PhotoWorldError, match='2 photos'):
        for i in range(2):
            cv2.imwrite(str(tmp_path / f'p{i}.jpg'), np.zeros((8, 8, 3), np.uint8))
        photo_world.read_sequence(tmp_path)
    folder, _source, _az0 = turn
    no_focal = tmp_path / 'no_focal'
    no_focal.mkdir()
    for p in sorted(folder.glob('*.jpg'))[:4]:
        (no_focal / p.name).write_bytes(p.read_bytes())
    with pytest.raises(PhotoWorldError, match='no focal lengths'):
        photo_world.read_sequence(no_focal)
    (no_focal / 'pano.txt').write_text('x.jpg 300\n')
    (no_focal / 'broken.jpg').write_bytes(b'not a jpeg')
    with pytest.raises(PhotoWorldError, match='not a readable image'):
        photo_world.read_sequence(no_focal)
    with pytest.raises(SimError, match='not a folder'):
        make_bag('rotation_sweep', tmp_path / 'x.mcap', seed=1, duration_s=1.0, world_photos=tmp_path / 'missing')
    with pytest.raises(SimError, match='rotation_sweep option'):
        make_bag('robot_arcs', tmp_path / 'y.mcap', seed=1, duration_s=1.0, world_photos=folder)
    assert not (tmp_path / 'x.mcap').exists()


@pytest.mark.skipif(not (SHARED_DATA / 'pano_grail').is_dir(), reason='../shared/data/pano_grail is not here')
def test_the_real_office_turn_is_laid_in_its_twenty_degree_steps():
    """pano_grail (18 hand-held photos of an office, shot about 20 deg apart, SOURCE.md): every
    neighbour pair is matched (no step falls back to the nominal one exactly), the steps are
    within 2 deg of 20 (hand-held: the first is 18.0, the last 21.7) with a median of 20 +- 0.3,
    the photos nearly level."""
    photos, focals = photo_world.read_sequence(SHARED_DATA / 'pano_grail')
    rotations = photo_world.photo_rotations(photos, focals)
    azimuths = np.degrees([math.atan2(R[0, 2], R[1, 2]) for R in rotations])
    steps = (np.diff(np.r_[azimuths, azimuths[0]]) + 180) % 360 - 180
    assert np.all(np.abs(np.abs(steps) - 20.0) < 2.0), steps
    assert abs(float(np.median(np.abs(steps))) - 20.0) < 0.3, steps
    assert np.all(np.abs(np.abs(steps) - 20.0) > 1e-6), steps
    elevations = np.degrees([math.asin(R[2, 2]) for R in rotations])
    assert np.all(np.abs(elevations) < 5.0), elevations
