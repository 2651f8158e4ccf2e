"""The static transforms of a bag's ``/tf_static`` read without ROS (the pip-only ROS has no
tf2_msgs wheel to subscribe with, so the graph runner and the evaluation read them here)."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

__all__ = ['TF_STATIC_TOPIC', 'StaticTransform', 'static_transforms']

from .bags import BagError, BagReader

logger = logging.getLogger(__name__)


#: Topic of the static transforms (tf2_msgs/msg/TFMessage).
TF_STATIC_TOPIC = '/tf_static'


@dataclass(frozen=True)
class StaticTransform:
    """One transform of ``/tf_static``: ``rotation`` (3x3) rotates vectors of the ``child``
    frame into the ``parent`` frame and ``translation`` (3,) is the child's origin in the parent
    (so p_parent = rotation @ p_child + translation). Frame ids without a leading slash."""

    parent: str
    child: str
    rotation: Any
    translation: Any


def static_transforms(reader: BagReader, topic: str = TF_STATIC_TOPIC) -> list[StaticTransform]:
    """Every transform of the bag's ``/tf_static``, read without ROS (rosbags decodes tf2_msgs).

    Nodes on the pip-only ROS cannot subscribe to /tf_static (no tf2_msgs wheel), so the graph
    runner reads it here and hands it to them. A later transform between the same two frames
    replaces an earlier one (tf2's rule for static transforms); a transform with a non-finite
    or non-unit quaternion, or an undecodable message, is skipped with a warning. An empty list
    when the bag has no /tf_static.
    """
    import numpy as np

    from ..core.rotations import is_valid_quat, quat_xyzw_to_matrix

    if reader.topics.get(topic) != 'tf2_msgs/msg/TFMessage':
        return []
    found: dict[tuple[str, str], StaticTransform] = {}
    for m in reader.messages([topic]):
        try:
            msg = reader.deserialize(m)
        except BagError as exc:
            logger.warning('%s: skipping an undecodable message: %s', topic, exc)
            continue
        for t in msg.transforms:
            parent, child = t.header.frame_id.lstrip('/'), t.child_frame_id.lstrip('/')
            r, p = t.transform.rotation, t.transform.translation
            q = np.array([r.x, r.y, r.z, r.w], dtype=float)
            if not is_valid_quat(q, 1e-3) or not np.all(np.isfinite([p.x, p.y, p.z])):
                logger.warning('%s: ignoring an invalid static transform %s -> %s', topic, parent, child)
                continue
            found.pop((parent, child), None)  # the latest one counts, in the order last given
            found[(parent, child)] = StaticTransform(
                parent, child, quat_xyzw_to_matrix(q),
                np.array([p.x, p.y, p.z], dtype=float),
            )
    return list(found.values())
