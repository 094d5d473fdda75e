"""Kernel launches, graph launches and device-to-host reads, counted while a run asks for them.

A GPU step is as fast as its longest chain of small launches and of host read-backs: every ``wp.launch`` costs a
few microseconds of host time, every read (``wp.array.numpy()`` of a CUDA array, a copy to the host) stops the host
until the device has finished. Counting them per step says how far a step is from a few captured graphs with no
read. :func:`counting` installs counters around Warp's entry points for the duration of a ``with`` block:

- ``launches``: kernels launched by ``wp.launch`` (not those only recorded with ``record_cmd=True``) and recorded
  launches replayed (``wp.Launch.launch``: the gas solver's, the multigrid's, ``kernels.launches.LaunchCache``'s);
- ``graph_launches``: captured graphs replayed (``wp.capture_launch``);
- ``reads``: ``wp.array.numpy()`` calls, ``wp.copy`` from a CUDA array to a host array, and each test of the
  condition of a ``wp.capture_if`` or ``wp.capture_while`` outside a graph capture (on CUDA a copy to pinned
  memory and a sync; inside a capture the test is a graph's conditional node, no read). On the CPU ``numpy()``
  is a view, not a copy, and a condition is read in place, but each is where a CUDA run of the same code reads
  the device back and waits for it: the count is the same on both devices.

The wrappers only count and call Warp's own functions with the same arguments, so results are bit for bit those
of an uncounted run; outside :func:`counting` Warp is untouched. :func:`paused` stops the counting for code that
reads on behalf of the measurement itself (an observer's statistics).
"""

from __future__ import annotations

import threading
from contextlib import contextmanager
from dataclasses import asdict, dataclass

import numpy as np

_lock = threading.Lock()


@dataclass
class Counts:
    launches: int = 0
    graph_launches: int = 0
    reads: int = 0

    def copy(self) -> "Counts":
        return Counts(**asdict(self))

    def __sub__(self, other: "Counts") -> "Counts":
        return Counts(self.launches - other.launches, self.graph_launches - other.graph_launches,
                      self.reads - other.reads)


_counts = Counts()
_depth = 0
_paused = 0
_saved = {}


def _install() -> None:
    import warp as wp

    launch, capture_launch, copy = wp.launch, wp.capture_launch, wp.copy
    replay, numpy = wp.Launch.launch, wp.array.numpy
    capture_if, capture_while = wp.capture_if, wp.capture_while
    _saved.update(launch=launch, capture_launch=capture_launch, copy=copy, replay=replay, numpy=numpy,
                  capture_if=capture_if, capture_while=capture_while)

    def host_test(condition) -> bool:
        """Whether Warp tests ``condition`` on the host (no capture on its device): a read."""
        device = getattr(condition, "device", None)
        return not _paused and device is not None and not device.is_capturing

    def counted_capture_if(condition, *args, **kwargs):
        if host_test(condition):
            _counts.reads += 1
        return capture_if(condition, *args, **kwargs)

    def counted_capture_while(condition, while_body, *args, **kwargs):
        if not host_test(condition) or not callable(while_body):
            return capture_while(condition, while_body, *args, **kwargs)
        _counts.reads += 1  # the first test

        def body(*a, **k):
            result = while_body(*a, **k)
            if not _paused:
                _counts.reads += 1  # the test after each pass
            return result

        return capture_while(condition, body, *args, **kwargs)

    def counted_launch(*args, **kwargs):
        if not _paused and not kwargs.get("record_cmd", False):
            _counts.launches += 1
        return launch(*args, **kwargs)

    def counted_replay(self, *args, **kwargs):
        if not _paused:
            _counts.launches += 1
        return replay(self, *args, **kwargs)

    def counted_capture_launch(*args, **kwargs):
        if not _paused:
            _counts.graph_launches += 1
        return capture_launch(*args, **kwargs)

    def counted_numpy(self, *args, **kwargs):
        if not _paused:
            _counts.reads += 1
        return numpy(self, *args, **kwargs)

    def counted_copy(dest, src, *args, **kwargs):
        if not _paused and getattr(getattr(src, "device", None), "is_cuda", False) and \
                getattr(getattr(dest, "device", None), "is_cpu", False):
            _counts.reads += 1
        return copy(dest, src, *args, **kwargs)

    wp.launch, wp.capture_launch, wp.copy = counted_launch, counted_capture_launch, counted_copy
    wp.Launch.launch, wp.array.numpy = counted_replay, counted_numpy
    wp.capture_if, wp.capture_while = counted_capture_if, counted_capture_while


def _uninstall() -> None:
    import warp as wp

    wp.launch, wp.capture_launch, wp.copy = _saved["launch"], _saved["capture_launch"], _saved["copy"]
    wp.Launch.launch, wp.array.numpy = _saved["replay"], _saved["numpy"]
    wp.capture_if, wp.capture_while = _saved["capture_if"], _saved["capture_while"]
    _saved.clear()


@contextmanager
def counting():
    """Count launches and reads inside the block (nested blocks share one set of counters)."""
    global _depth
    with _lock:
        if _depth == 0:
            _install()
        _depth += 1
    try:
        yield _counts
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                _uninstall()


def start() -> None:
    """Install the counters until :func:`stop` (a run that counts from its build to its summary)."""
    global _depth
    with _lock:
        if _depth == 0:
            _install()
        _depth += 1


def stop() -> None:
    global _depth
    with _lock:
        if _depth == 0:
            return
        _depth -= 1
        if _depth == 0:
            _uninstall()


def active() -> bool:
    return _depth > 0


@contextmanager
def paused():
    """No counting inside the block (reads made for the measurement, not by the step)."""
    global _paused
    _paused += 1
    try:
        yield
    finally:
        _paused -= 1


def snapshot() -> Counts:
    """The counts so far (a copy)."""
    return _counts.copy()


class PerStep:
    """Observer: the launches, graph launches and reads of each step (counted between consecutive
    ``after_step`` calls, so what the run loop does between steps, outputs included, belongs to the next step).
    :meth:`medians` over the steady steps (those after the first ``skip``, which compile, record and capture)."""

    def __init__(self):
        self.rows = []
        self._last = None

    def after_step(self, solver) -> None:
        now = snapshot()
        if self._last is not None:
            d = now - self._last
            self.rows.append((d.launches, d.graph_launches, d.reads))
        self._last = now

    def medians(self, skip: int = 2) -> dict:
        rows = np.asarray(self.rows[skip:] if len(self.rows) > skip else self.rows, dtype=np.float64)
        if rows.size == 0:
            return {"launches_per_step": None, "graph_launches_per_step": None, "device_reads_per_step": None}
        med = np.median(rows, axis=0)
        return {"launches_per_step": float(med[0]), "graph_launches_per_step": float(med[1]),
                "device_reads_per_step": float(med[2]), "counted_steps": int(len(rows))}


__all__ = ["Counts", "PerStep", "active", "counting", "paused", "snapshot", "start", "stop"]
