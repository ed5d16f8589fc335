"""The shared frame of a run: the first robot's first camera frame, and ground truth moved into it.

Every fused trajectory of a run is in this one frame. Ground truth comes in each sequence's own world frame
(the simulator's city, KITTI's first camera of the drive), so it is moved into the shared frame as the run
measures its ATE::

    T_shared_cam_gt = inverse(T_world_cam_gt of the first robot's first frame) @ T_world_cam_gt
"""

from __future__ import annotations

import numpy as np

from shgm_slam.geometry import se3
from shgm_slam.types import Sequence


def shared_frame_ground_truth(robots: dict[str, Sequence], gt_shared_frame: bool = True) -> dict[str, np.ndarray]:
    """Each robot's ground truth ``T_shared_cam`` (N, 4, 4) in the run's shared frame.

    Args:
        robots: robot name -> sequence, in run order (the first robot defines the shared frame).
        gt_shared_frame: the sequences' ground truths share one world frame (our simulator; ranges of
            one KITTI sequence). When False only the first robot's ground truth can be placed.

    Returns:
        robot -> poses, for the robots whose ground truth can be put in the shared frame (none when
        the first robot has no ground truth).
    """
    names = list(robots)
    if not names or robots[names[0]].gt_poses is None:
        return {}
    T_shared_world = se3.inverse(np.asarray(robots[names[0]].gt_poses)[0])
    placed = names if gt_shared_frame else names[:1]
    return {r: T_shared_world @ np.asarray(robots[r].gt_poses) for r in placed if robots[r].gt_poses is not None}
