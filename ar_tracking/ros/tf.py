"""TF broadcasting without tf2_ros: TransformStamped on ``/tf`` and latched on ``/tf_static``.

tf2_ros's TransformBroadcaster and StaticTransformBroadcaster do nothing more than this (same
topics, same QoS), and tf2_ros is not on the pip-only path; tf2_msgs is (built by
./ar-tracking.sh from interfaces/tf2_msgs), or comes from the ROS install. Where neither has
it, :func:`tf_message_class` returns None and the nodes say once that they publish no TF.

The publishers are plain rclpy publishers, not the counted ones of :class:`TrackingNode`: TF
is a side channel that no node of the graph waits for, so the lockstep runner must not count it.
"""
from __future__ import annotations

from typing import Any, Callable, Iterable

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .conversions import set_quaternion, to_stamp

#: tf2_ros's DynamicBroadcasterQoS: reliable, volatile, keep last 100.
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE, history=HistoryPolicy.KEEP_LAST)
#: tf2_ros's StaticBroadcasterQoS: reliable, transient local, keep last 1 (latched).
TF_STATIC_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)


def tf_message_class() -> Any:
    """tf2_msgs/msg/TFMessage, or None where this Python has no tf2_msgs."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        return None
    return TFMessage


def transform_stamped(t_ns: int, parent: str, child: str, R_parent_child: np.ndarray,
                      translation: Iterable[float] | None = None) -> TransformStamped:
    """A TransformStamped parent -> child: ``R_parent_child`` (3x3) rotates child vectors into
    the parent, ``translation`` is the child's origin in the parent (m; zero when None)."""
    tf = TransformStamped()
    tf.header.stamp = to_stamp(int(t_ns))
    tf.header.frame_id = parent
    tf.child_frame_id = child
    set_quaternion(tf.transform.rotation, np.asarray(R_parent_child, dtype=float))
    if translation is not None:
        x, y, z = (float(v) for v in translation)
        tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = x, y, z
    return tf


class TfBroadcaster:
    """Publishes transforms on ``/tf`` (``static=False``) or ``/tf_static`` (``static=True``).

    A static broadcaster keeps every transform it was given, one per child frame, and publishes
    them all each time (the latched topic holds one message, as with tf2_ros's
    StaticTransformBroadcaster). When the type is missing, :attr:`available` is False and
    :meth:`send` does nothing.

    ``/tf`` is volatile: a transform sent while no subscription has matched reaches nobody, so
    :meth:`send` then skips it (and a node asks :attr:`listened` before building one). In a
    lockstep run nothing outside the process can subscribe (discovery is off), which made the
    hybrid filter's /tf ~0.1 s of a 60 s bench run spent on messages no one received.
    """

    def __init__(self, node: Any, static: bool = False) -> None:
        self.static = static
        self._type = tf_message_class()
        self._static: dict[str, TransformStamped] = {}
        self._pub = None
        if self._type is not None:
            self._pub = node.create_publisher(self._type, '/tf_static' if static else '/tf',
                                              TF_STATIC_QOS if static else TF_QOS)

    @property
    def available(self) -> bool:
        return self._pub is not None

    @property
    def listened(self) -> bool:
        """Whether a transform sent now can reach anyone: ``/tf_static`` always (latched for
        later subscribers), ``/tf`` only while a subscription has matched."""
        return self._pub is not None and (self.static or self._pub.get_subscription_count() > 0)

    def send(self, transforms: TransformStamped | list[TransformStamped]) -> None:
        """Publish (``/tf_static``: with every transform sent before). Callers on ``/tf`` ask
        :attr:`listened` first, before building the transforms."""
        if self._pub is None:
            return
        items = [transforms] if isinstance(transforms, TransformStamped) else list(transforms)
        if self.static:
            for tf in items:
                self._static[tf.child_frame_id] = tf
            items = list(self._static.values())
        msg = self._type()
        msg.transforms = items
        self._pub.publish(msg)

    def destroy(self, node: Any) -> None:
        if self._pub is not None:
            node.destroy_publisher(self._pub)
            self._pub = None


def subscribe_static_transforms(node: Any, callback: Callable[[list[Any]], None]) -> bool:
    """Subscribe ``node`` to ``/tf_static`` (latched, as tf2_ros does) and call ``callback``
    with each message's transforms as io.bags.StaticTransform - the form in which the graph
    runner hands a bag's static transforms to a node. False where tf2_msgs is missing (the
    pip-only path before ./ar-tracking.sh built it): the runner's hand-over is all there is."""
    TFMessage = tf_message_class()
    if TFMessage is None:
        return False
    from ..io.static_tf import StaticTransform
    from ..core.rotations import quat_xyzw_to_matrix

    def on_tf(msg: Any) -> None:
        items = []
        for tf in msg.transforms:
            q, t = tf.transform.rotation, tf.transform.translation
            items.append(StaticTransform(parent=tf.header.frame_id.lstrip('/'), child=tf.child_frame_id.lstrip('/'),
                                         rotation=quat_xyzw_to_matrix(np.array([q.x, q.y, q.z, q.w])),
                                         translation=np.array([t.x, t.y, t.z])))
        callback(items)

    # tf2_ros's static listener: transient local, a deep history (several broadcasters at once)
    listener_qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)
    node.create_subscription(TFMessage, '/tf_static', on_tf, listener_qos)
    return True
