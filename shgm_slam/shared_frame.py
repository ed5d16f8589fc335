"""The shared frame of a run: the first robot's first camera frame, and ground truth moved into it.

Every fused trajectory of a run is in this one frame. Ground truth comes in each sequence's own world frame
(the simulator's city, KITTI's first camera of the drive), so it is moved into the shared frame as the run
measures its ATE::

    T_shared_cam_gt = inverse(T_world_cam_gt of the first robot's first frame) @ T_world_cam_gt
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from shgm_slam.geometry import se3
from shgm_slam.types import Sequence


def shared_from_world(first_gt_poses: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_shared_world``: the inverse of the first robot's first ground-truth pose, from its (N, 4, 4)
    ``T_world_cam`` (N >= 1)."""
    return se3.inverse(np.asarray(first_gt_poses[0], dtype=np.float64))


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
    T_shared_world = shared_from_world(robots[names[0]].gt_poses)
    placed = names if gt_shared_frame else names[:1]
    return {r: T_shared_world @ np.asarray(robots[r].gt_poses) for r in placed if robots[r].gt_poses is not None}


class SharedTruth:
    """Ground-truth camera positions in a run's shared frame, one frame at a time (the viewer's error series).

    As ``shared_frame_ground_truth``, but per frame and without copying whole trajectories: a live run's
    ground truth grows frame by frame, and the viewer asks at every frame.

    Args:
        robots: robot name -> sequence, in run order (the first robot defines the shared frame); read at each
            call, so sequences that grow (``data.stream.FrameStream``) are followed.
        gt_shared_frame: the sequences' ground truths share one world frame (as ``shared_frame_ground_truth``);
            when False only the first robot's frames have a position.
    """

    def __init__(self, robots: Mapping[str, Sequence], gt_shared_frame: bool = True) -> None:
        self.robots = robots
        self.gt_shared_frame = gt_shared_frame
        self._T_shared_world: np.ndarray | None = None

    def position(self, robot: str, index: int) -> np.ndarray | None:
        """(3,) ground-truth position of ``robot``'s camera at frame ``index`` in the shared frame, metres, or None
        (no ground truth for that frame, or none that the shared frame can hold)."""
        names = list(self.robots)
        if robot not in self.robots or not names or (robot != names[0] and not self.gt_shared_frame):
            return None
        gt = self.robots[robot].gt_poses
        if gt is None or not 0 <= index < len(gt):
            return None
        if self._T_shared_world is None:
            first = self.robots[names[0]].gt_poses
            if first is None or not len(first):
                return None
            self._T_shared_world = shared_from_world(first)
        T = self._T_shared_world
        return T[:3, :3] @ np.asarray(gt[index][:3, 3], dtype=np.float64) + T[:3, 3]
