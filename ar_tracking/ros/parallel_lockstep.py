"""Lockstep over node processes: ``ar-tracking run BAG --executor processes`` without ``--rate``.

The in-process lockstep (:mod:`~ar_tracking.ros.runner`) runs every node on one thread, one
input at a time: that is what makes two runs byte-identical, and what keeps a graph's wall time
at the sum of its nodes' work. Here every node runs in a process of its own
(:mod:`~ar_tracking.ros.node_process`) and the runner carries the messages over the processes'
pipes instead of DDS, so that nodes work in parallel while each still sees a fixed sequence.

Every bag message the graph consumes is one *step*. A node's inputs of a step are the bag
message (if it subscribes to its topic) followed by what the nodes upstream of it published
while processing that step, node by node in the graph's topological order, each in its
publication order; a KEEP_LAST subscription keeps the newest ``depth`` of a step's messages
on its topic (the others are booked as superseded or dropped, as the in-process ledger books a
burst). A node gets step k's inputs once every node upstream of it has returned its outputs of
step k, and always after its own step k-1; nothing else waits. So the mapper works on frame k
while the IMU path works through the samples before it, and the hybrid takes the samples after
frame k once the mapper's estimate of frame k is in. Outputs are written in step order with
the log time of the step's message, ordered by topic as in-process, so two runs give
byte-identical bags.

The graph must be acyclic (no node's output reaches itself through other nodes); a cyclic
graph is refused with a RunError that names the in-process lockstep instead. Messages a node
publishes before its first input (in its constructor or on the static transforms) are recorded
and delivered downstream before the first step. The node process's side is
:mod:`~ar_tracking.ros.lockstep_child`.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from multiprocessing.connection import wait
from typing import Any, Callable, Iterable

from .graph_plan import RunError
from .node_process import NodeProcess, NodeProcessError
from .run_state import Recorder, RunResult, book

logger = logging.getLogger(__name__)

#: How many steps (bag messages) the runner reads ahead of the oldest one not yet written: the
#: slack that lets an upstream node run ahead of a slow one (~2 s of the bench bag).
WINDOW_STEPS = 512
#: A node that returns nothing for this long while it has inputs is reported and the run ends.
STEP_TIMEOUT_S = 120.0
#: After this many inputs in a row on one topic that a node could not read, the run stops.
MAX_CONSECUTIVE_LOSSES = 20

Batch = list[tuple[str, bytes]]


# -- the runner's side --------------------------------------------------------------------

@dataclass
class _Step:
    """One bag message the graph consumes, and what each node published on it."""

    log_time_ns: int
    #: (topic, raw) of the fed message; None for the prelude (step -1)
    feed: tuple[str, bytes] | None
    #: (topic, raw, msgtype) written before the outputs (the message, if it is copied too)
    copy: tuple[str, bytes, str] | None
    #: per node index: what it published on this step (None while not yet known)
    outputs: list[Batch | None]
    #: copy-only messages read after this one, written after its outputs
    trailing: list[tuple[str, int, bytes, str]] = field(default_factory=list)


def topological_order(handles: list[NodeProcess]) -> tuple[list[int], list[list[int]]]:
    """The node indices in an order where every node comes after the nodes whose outputs it
    subscribes to, and per node those upstream nodes (in that order); RunError on a cycle.
    Outputs are the node classes' ``OUTPUTS`` (what their counted publishers carry; TF is a
    side channel no node of the graph waits for, as in-process)."""
    n = len(handles)
    outputs = [{'/' + t.lstrip('/') for t in h.node_class.OUTPUTS} for h in handles]
    upstream = [[j for j in range(n) if set(handles[i].subscription_topics) & outputs[j]] for i in range(n)]
    order: list[int] = []
    placed: set[int] = set()
    while len(order) < n:
        ready = [i for i in range(n) if i not in placed and all(j in placed for j in upstream[i])]
        if not ready:
            cycle = ', '.join(handles[i].name for i in range(n) if i not in placed)
            raise RunError(f'{cycle}: their topics form a cycle; run them in one process '
                           '(--executor events) for lockstep')
        order.extend(ready)
        placed.update(ready)
    rank = {i: r for r, i in enumerate(order)}
    return order, [sorted(up, key=rank.__getitem__) for up in upstream]


class ParallelLockstep:
    """Feeds a bag to node processes step by step (module docstring) and records their outputs."""

    def __init__(self, handles: list[NodeProcess], recorder: Recorder, result: RunResult,
                 record: Callable[[str, bytes], None], window_steps: int = WINDOW_STEPS, step_timeout_s: float = STEP_TIMEOUT_S) -> None:
        self.handles = handles
        self.recorder = recorder
        self.writer = recorder.writer
        self.result = result
        #: takes one output into the step's batch (``recorder.add``, with the output taps)
        self.record = record
        self.window_steps = window_steps
        self.step_timeout_s = step_timeout_s
        #: the nodes in topological order, and per node the nodes upstream of it (connect())
        self.order: list[int] = []
        self.upstream: list[list[int]] = []
        #: per node: subscribed topic -> KEEP_LAST depth (None: keep all)
        self.depths: list[dict[str, int | None]] = []
        self.steps: dict[int, _Step] = {}
        self.first = 0   # the oldest step not yet written
        self.next_seq = 0   # the seq the next fed message gets
        self.next_send = [0] * len(handles)   # per node: the next step to decide
        self.in_flight = [0] * len(handles)   # per node: steps sent, outputs not yet back
        #: per node: what it published before its first input
        self._preludes: list[Batch] = [[] for _ in handles]
        self._losses: dict[tuple[int, str], int] = defaultdict(int)  # (node, fed topic) -> in a row
        self._last_heard = time.monotonic()

    # -- start ------------------------------------------------------------------------

    def connect(self) -> None:
        """Wait for every node process to build its node and take what it published before
        its first input (delivered downstream as step -1)."""
        preludes: list[Batch] = []
        try:
            for h in self.handles:
                h.wait_created()
            self.order, self.upstream = topological_order(self.handles)
            self.depths = [dict(h.subscription_depths) for h in self.handles]
            for h in self.handles:
                preludes.append(list(h.wait_ready()[0] or []))
        except NodeProcessError as exc:
            raise RunError(f'cannot start {exc}') from exc
        if any(preludes):
            self.first = self.next_seq = -1
            self.next_send = [-1] * len(self.handles)
            self.steps[-1] = _Step(0, None, None, [None] * len(self.handles))
            self._preludes = preludes

    def finish(self) -> None:
        """After the feed: stop every node process, with its counts (callbacks, publications)
        and its CPU seconds into the run result."""
        for h in self.handles:
            h.stop()
            if h.cpu_s is not None:
                self.result.live_cpu_s[h.name] = h.cpu_s

    # -- the feed ---------------------------------------------------------------------

    def play(self, messages: Iterable[Any], feed_topics: set[str], copy_topics: set[str], stop: threading.Event,
             max_messages: int | None = None, progress: Callable[[int, int], None] | None = None, total: int = 0) -> None:
        """Read the bag, keep at most ``window_steps`` steps ahead of the last written one,
        and return once every step read has been written (or on a stop request)."""
        result = self.result
        it = iter(messages)
        done = 0
        exhausted = False
        while True:
            while not exhausted and self.next_seq - self.first < self.window_steps:
                if stop.is_set() or (max_messages is not None and done >= max_messages):
                    exhausted = True
                    break
                msg = next(it, None)
                if msg is None:
                    exhausted = True
                    break
                done += 1
                if msg.topic in feed_topics:
                    copy = (msg.topic, msg.rawdata, msg.msgtype) if msg.topic in copy_topics else None
                    self._add_step(msg.log_time_ns, (msg.topic, msg.rawdata), copy)
                    result.input_messages += 1
                elif msg.topic in copy_topics:
                    self._add_copy(msg.topic, msg.log_time_ns, msg.rawdata, msg.msgtype)
                if progress is not None:
                    progress(done, total)
            self._advance()
            self._write_ready()
            if self.first == self.next_seq and (exhausted or stop.is_set()):
                return
            if stop.is_set() and not any(self.in_flight):
                return  # Ctrl-C: what is written stays; steps no node is working on are left
            if exhausted or self.next_seq - self.first >= self.window_steps or any(self.in_flight):
                self._receive(timeout_s=0.5)

    def _add_step(self, log_time_ns: int, feed: tuple[str, bytes], copy: tuple[str, bytes, str] | None) -> None:
        seq = self.next_seq
        if -1 in self.steps and self.steps[-1].log_time_ns == 0:
            self.steps[-1].log_time_ns = log_time_ns  # the prelude is written at the first step's time
        self.steps[seq] = _Step(log_time_ns, feed, copy, [None] * len(self.handles))
        self.next_seq = seq + 1

    def _add_copy(self, topic: str, log_time_ns: int, raw: bytes, msgtype: str) -> None:
        """A message only copied to the output: after the outputs of the step before it."""
        if self.first == self.next_seq:
            self.writer.write(topic, log_time_ns, raw, msgtype=msgtype)
        else:
            self.steps[self.next_seq - 1].trailing.append((topic, log_time_ns, raw, msgtype))

    # -- scheduling ---------------------------------------------------------------------

    def _advance(self) -> None:
        """Send every node the steps whose inputs are complete, in step order, batched per
        node; a step with no input for a node has no output from it."""
        progressed = True
        while progressed:
            progressed = False
            chunks: dict[int, list[tuple[int, Batch]]] = defaultdict(list)
            for i in self.order:
                while self.next_send[i] < self.next_seq:
                    seq = self.next_send[i]
                    step = self.steps[seq]
                    if any(step.outputs[j] is None for j in self.upstream[i]):
                        break
                    batch = self._inputs(i, step)
                    if batch:
                        chunks[i].append((seq, batch))
                        self.in_flight[i] += 1
                    else:
                        step.outputs[i] = list(self._preludes[i]) if seq == -1 else []
                        progressed = True
                    self.next_send[i] = seq + 1
            for i, chunk in chunks.items():
                self._send(i, chunk)

    def _inputs(self, i: int, step: _Step) -> Batch:
        """Node ``i``'s inputs of ``step``: the fed message, then its upstream nodes' outputs,
        each subscription keeping the newest ``depth`` of them."""
        depths = self.depths[i]
        batch: Batch = []
        if step.feed is not None and step.feed[0] in depths:
            batch.append(step.feed)
        for j in self.upstream[i]:
            batch.extend(item for item in step.outputs[j] or () if item[0] in depths)
        if len(batch) > 1:
            batch = self._within_depth(i, batch)
        return batch

    def _within_depth(self, i: int, batch: Batch) -> Batch:
        """``batch`` without the oldest messages of each KEEP_LAST subscription of node ``i``
        that it holds more of than the depth, booked in the run result (superseded for depth
        1, dropped for deeper queues)."""
        counts: dict[str, int] = defaultdict(int)
        for topic, _ in batch:
            counts[topic] += 1
        over = {t: n - d for t, n in counts.items() if (d := self.depths[i][t]) is not None and n > d}
        if not over:
            return batch
        kept: Batch = []
        skip = dict(over)
        for topic, raw in batch:
            if skip.get(topic, 0) > 0:
                skip[topic] -= 1  # the oldest of the step's messages on it
                continue
            kept.append((topic, raw))
        for topic, n in over.items():
            book(self.result.superseded if self.depths[i][topic] == 1 else self.result.dropped,
                 self.handles[i].name, topic, n)
        return kept

    def _send(self, i: int, chunk: list[tuple[int, Batch]]) -> None:
        h = self.handles[i]
        try:
            h.send_steps(chunk)
        except (OSError, ValueError) as exc:
            raise RunError(f'{h.name} is gone ({h.died() or exc})') from None

    def _receive(self, timeout_s: float) -> None:
        """Take the outputs the node processes have sent back (waits up to ``timeout_s``)."""
        conns = {h.connection: i for i, h in enumerate(self.handles) if self.in_flight[i]}
        if not conns:
            return
        ready = wait(list(conns), timeout=timeout_s)
        if not ready:
            self._check_alive()
            return
        self._last_heard = time.monotonic()
        for conn in ready:
            i = conns[conn]
            h = self.handles[i]
            try:
                report = h.receive_outputs()
            except NodeProcessError as exc:
                self.result.failed_nodes[h.name] = h.failure or str(exc)
                raise RunError(f'{h.name} died: {h.failure or exc}') from None
            for seq, outs, unread in report:
                self.in_flight[i] -= 1
                self.steps[seq].outputs[i] = (self._preludes[i] + outs) if seq == -1 else outs
                self._count_unread(i, seq, unread)

    def _check_alive(self) -> None:
        for h in self.handles:
            why = h.died()
            if why is not None:
                self.result.failed_nodes[h.name] = why
                raise RunError(f'{h.name} died: {why}')
        if time.monotonic() - self._last_heard > self.step_timeout_s:
            waiting = ', '.join(self.handles[i].name for i in range(len(self.handles)) if self.in_flight[i])
            raise RunError(f'{waiting}: no output for {self.step_timeout_s:g} s')

    def _count_unread(self, i: int, seq: int, unread: list[str]) -> None:
        """Inputs a node could not read (not of the declared type): lost, as in-process; a long
        run of them on one topic ends the run."""
        step = self.steps[seq]
        fed = step.feed[0] if step.feed is not None else None
        for topic in unread:
            self.result.lost_deliveries += 1
            book(self.result.lost, self.handles[i].name, topic, 1)
        if fed is not None and fed in self.depths[i]:
            key = (i, fed)
            if fed in unread:
                self._losses[key] += 1
                logger.warning('%s: %s message does not read as its type; lost', self.handles[i].name, fed)
                if self._losses[key] >= MAX_CONSECUTIVE_LOSSES:
                    raise RunError(f'the nodes received none of the last {self._losses[key]} messages on {fed}; '
                                   'stopping (are they of the declared type?)')
            else:
                self._losses[key] = 0

    def _write_ready(self) -> None:
        """Write every step, oldest first, whose outputs are all known."""
        recorder, record = self.recorder, self.record
        while self.first < self.next_seq:
            step = self.steps[self.first]
            if any(out is None for out in step.outputs):
                return
            if step.copy is not None:
                topic, raw, msgtype = step.copy
                self.writer.write(topic, step.log_time_ns, raw, msgtype=msgtype)
            for i in self.order:
                for topic, raw in step.outputs[i]:  # type: ignore[union-attr]
                    record(topic, raw)
            recorder.flush(step.log_time_ns)
            for topic, log_time_ns, raw, msgtype in step.trailing:
                self.writer.write(topic, log_time_ns, raw, msgtype=msgtype)
            del self.steps[self.first]
            self.first += 1
