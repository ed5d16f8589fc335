"""Sequence readers and writers: KITTI odometry folders and our layout (images, depth, labels, poses).

``open_sequence("path[:start-end]")`` returns a lazily loading ``types.Sequence``; ``ArraySequence`` holds
frames given in memory; ``SequenceWriter`` streams frames into our layout.
"""

from shgm_slam.data.base import (
    SEQUENCE_READERS,
    SequenceLayout,
    SequenceView,
    detect_layout,
    open_sequence,
    parse_sequence_spec,
)
from shgm_slam.data.kitti import KittiSequence
from shgm_slam.data.memory import ArraySequence
from shgm_slam.data.sequence import SequenceWriter, ShgmSequence, decode_depth, encode_depth

__all__ = [
    "SEQUENCE_READERS",
    "ArraySequence",
    "KittiSequence",
    "SequenceLayout",
    "SequenceView",
    "SequenceWriter",
    "ShgmSequence",
    "decode_depth",
    "detect_layout",
    "encode_depth",
    "open_sequence",
    "parse_sequence_spec",
]
