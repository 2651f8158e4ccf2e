"""The root of every error the package raises on purpose.

Each subpackage has its own error classes (the io bag readers :class:`~ar_tracking.io.bags.BagError`,
the annotation store :class:`~ar_tracking.core.annotations.store.StoreError`, the graph runner
:class:`~ar_tracking.ros.runner.RunError`, ...) and every one of them derives from
:class:`ArTrackingError`, so that a caller (the CLI, a script, a test) can catch "anything this
package reports" in one clause and let real bugs (TypeError, AttributeError) through. Classes
that were ValueErrors stay ValueErrors as well, so existing ``except ValueError`` still works.

This module imports nothing: the algorithm cores may import it without pulling in io or ROS.
"""
from __future__ import annotations


class ArTrackingError(Exception):
    """An error this package raises on purpose: bad input, a file it cannot use, a graph that
    cannot run. The message is one line meant for the user."""
