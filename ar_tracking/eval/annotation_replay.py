"""Replay the annotation matcher alone on a recorded graph output, with other parameters.

Measuring a matcher change end to end means simulating the spots again and running the whole
graph on each (``bench_graph_spots``: minutes per spot). The matcher's inputs - the browsing
panorama (``panorama/image``, ``panorama/tiles``), its orientation (``panorama/orientation``,
``orientation/global``, ``orientation/panorama_in_world``) and the GPS fix - are all in that run's
output bag, so the matcher can be fed them again in log-time order, with other parameters or
other code, in seconds. The replayed ``annotations/markers`` replace the recorded ones in a copy
of the bag, which :func:`~ar_tracking.eval.annotation_metrics.evaluate_annotations` scores as
usual.

The replay is a guide, not the figure: in the graph the matcher's callbacks of one lockstep step
can come in another order than the bag's log times, so a label can differ from the run's. Tune
on replays of development spots and report a fresh end-to-end run.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable

from ..io.bags import BagReader, BagWriter
from .annotation_metrics import evaluate_annotations

def replay_matcher(out_bag: str | Path, store_path: str | Path, replayed_bag: str | Path,
                   params: dict[str, Any] | None = None, labels: Iterable[str] | None = None,
                   context: Any = None) -> dict[str, Any] | None:
    """Feed ``annotation_matcher`` (store ``store_path``, node parameters ``params``) the matcher
    inputs recorded in ``out_bag``, write ``replayed_bag`` (``out_bag`` with the replayed matcher
    outputs) and score it (``evaluate_annotations``; ``labels``: only these anchors). ``context``:
    an initialised rclpy Context (default: one made and shut down here). Needs rclpy."""
    import rclpy
    from rclpy.serialization import serialize_message

    from ..nodes.annotation_matcher import AnnotationMatcherNode
    from ..ros.params import params_for_node, to_overrides
    from ..ros.player import decode

    own = context is None
    if own:
        from rclpy.context import Context

        context = Context()
        rclpy.init(context=context)
    node = None
    try:
        prm = params_for_node('annotation_matcher', [])
        prm.update({'store_path': str(store_path), **(params or {})})
        node = AnnotationMatcherNode(context=context, parameter_overrides=to_overrides(prm))
        outputs = {'/' + t.lstrip('/'): ty for t, ty in AnnotationMatcherNode.OUTPUTS.items()}
        published: list[tuple[str, Any]] = []
        for pub in node.publishers:
            if pub.topic_name in outputs:
                pub.publish = lambda m, t=pub.topic_name: published.append((t, m))  # type: ignore[method-assign, misc]
        # the node's own (guarded) subscription callbacks: a message that raises is skipped, as in the
        # graph; a raw subscription (a CDR view, ros.cdr_views) takes the bytes as they are
        callbacks = {s.topic_name: (s.callback, s.raw) for s in node.subscriptions}
        with BagReader(out_bag) as bag, BagWriter(replayed_bag, overwrite=True) as writer:
            for msg in bag.messages():
                if msg.topic in outputs:
                    continue
                writer.write(msg.topic, msg.log_time_ns, msg.rawdata, msgtype=msg.msgtype)
                if msg.topic in callbacks:
                    callback, raw = callbacks[msg.topic]
                    callback(bytes(msg.rawdata) if raw else decode(bytes(msg.rawdata), msg.msgtype))
                    for topic, out in published:
                        data = bytes(out) if isinstance(out, (bytes, bytearray, memoryview)) else serialize_message(out)
                        writer.write(topic, msg.log_time_ns, data, msgtype=outputs[topic])
                    published.clear()
    finally:
        if node is not None:
            node.destroy_node()
        if own:
            rclpy.try_shutdown(context=context)
    return evaluate_annotations(replayed_bag, labels=labels)
