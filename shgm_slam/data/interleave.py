"""Interleaving several robots' frames in time (the single-process run's schedule)."""

from __future__ import annotations

import heapq
import logging
from collections.abc import Iterator

import numpy as np

from shgm_slam.types import Sequence

log = logging.getLogger(__name__)


def interleave(sequences: dict[str, Sequence]) -> Iterator[tuple[str, int]]:
    """Yield ``(robot, frame_index)`` in order of time since each robot's first frame; at equal times the
    first robot (the reference) goes first, then the others by name: the order in which the map server
    takes keyframes from robot processes (``server.ordering``)."""
    heap = []
    for r_i, (name, seq) in enumerate(sequences.items()):
        if len(seq):
            t = np.asarray(seq.timestamps_s, dtype=np.float64)
            heap.append((0.0, min(r_i, 1), name, 0, t))
    heapq.heapify(heap)
    while heap:
        _, rank, name, i, t = heapq.heappop(heap)
        yield name, i
        if i + 1 < len(t):
            heapq.heappush(heap, (float(t[i + 1] - t[0]), rank, name, i + 1, t))
