"""The street scene of rotation_sweep, as one import: a thin re-export of its modules.

A procedural 360-degree outdoor spot (a town square): a ring of buildings with windows, doors,
shop signs and awnings, trees and lamp posts in front of them, a distant skyline, paved ground and
a cloudy sky, as textured planes in ENU. Three steps, each cheap enough for a one-minute bag to be
made in seconds: :func:`build_world` (seed only, :mod:`.layout`), :func:`make_lighting` (seed and
session, :mod:`.lighting`), :func:`render_panorama` (:mod:`.render`); :class:`FrameRenderer`
(:mod:`.camera`) turns the panorama into 8-bit camera frames. The data types are in
:mod:`.model`, the texture painters in :mod:`.street_textures` and :mod:`.textures`.

Kept because eval/ and robot_arcs import the street scene from here; new code imports the
concern modules directly.
"""
from __future__ import annotations

from .camera import FrameRenderer, PinholeCamera
from .layout import build_world
from .lighting import make_lighting
from .model import (EYE_HEIGHT_M, GAMMA, PANO_HEIGHT, PANO_WIDTH, Anchor, Lighting, Panorama, Plane,
                    World, direction_to_pano, pano_directions)
from .render import render_panorama
from .rng import rng_stream

__all__ = ['EYE_HEIGHT_M', 'GAMMA', 'PANO_HEIGHT', 'PANO_WIDTH', 'Anchor', 'FrameRenderer', 'Lighting',
           'Panorama', 'PinholeCamera', 'Plane', 'World', 'build_world', 'direction_to_pano',
           'make_lighting', 'pano_directions', 'render_panorama', 'rng_stream']
