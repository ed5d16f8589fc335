"""The single-process run's schedule: every robot's frames in order of time since its own first frame."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from shgm_slam.data.interleave import interleave


@dataclass
class _Times:
    """The part of a sequence the schedule reads: its frame times."""

    timestamps_s: np.ndarray

    def __len__(self) -> int:
        return len(self.timestamps_s)


def test_frames_come_in_time_since_each_robots_start_reference_first_at_ties() -> None:
    sequences = {
        "car1": _Times(np.array([100.0, 100.25, 100.5, 100.75])),  # the reference: 4 Hz (times exact in binary)
        "uav": _Times(np.array([5.0, 5.125, 5.25, 5.375, 5.5])),  # 8 Hz, its own clock
        "car2": _Times(np.array([0.0, 0.25, 0.5])),
    }
    order = list(interleave(sequences))
    assert sorted(order) == sorted((r, i) for r, s in sequences.items() for i in range(len(s)))  # each frame once
    for robot, seq in sequences.items():  # each robot's frames in its own order
        assert [i for r, i in order if r == robot] == list(range(len(seq)))
    since = [sequences[r].timestamps_s[i] - sequences[r].timestamps_s[0] for r, i in order]
    assert all(a <= b + 1e-12 for a, b in pairwise(since))
    # at t = 0 and t = 0.25: the reference first, then the others by name
    assert order[:3] == [("car1", 0), ("car2", 0), ("uav", 0)]
    assert order[4:7] == [("car1", 1), ("car2", 1), ("uav", 2)]


def test_an_empty_sequence_contributes_nothing() -> None:
    order = list(interleave({"car1": _Times(np.zeros(0)), "car2": _Times(np.array([1.0, 2.0]))}))
    assert order == [("car2", 0), ("car2", 1)]
