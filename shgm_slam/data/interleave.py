"""Interleaving several robots' frames in time (the single-process run's schedule)."""

from __future__ import annotations

import heapq
import logging
from collections.abc import Iterator

import numpy as np

from shgm_slam.types import Sequence

log = logging.getLogger(__name__)


def interleave(sequences: dict[str, Sequence]) -> Iterator[tuple[str, int]]:
    """Yield ``(robot, frame_index)`` in order of time since each robot's first frame."""
    heap = []
    for r_i, (name, seq) in enumerate(sequences.items()):
        if len(seq):
            t = np.asarray(seq.timestamps_s, dtype=np.float64)
            heap.append((0.0, r_i, name, 0, t))
    heapq.heapify(heap)
    while heap:
        _, r_i, name, i, t = heapq.heappop(heap)
        yield name, i
        if i + 1 < len(t):
            heapq.heappush(heap, (float(t[i + 1] - t[0]), r_i, name, i + 1, t))
