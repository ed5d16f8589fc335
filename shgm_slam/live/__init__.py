"""Frames fed one by one, as cameras deliver them: the whole system (front ends, map server, viewer, results
folder) stepped by ``LiveRun.add_frame`` instead of a recorded sequence.

Each robot's first frames set its data-derived settings (extraction range, blob size, odometry voxel: the camera's
height above the ground and the depth it sees, ``scene_scale``), so a robot's frames are held until it has sent
enough of them (``ScaleSampler``: five frames that show the ground, 0.5 s apart: 21 frames at 10 fps where the
ground shows from the start, at most ``SAMPLE_SPAN_FRAMES``). The run starts once the first robot (the shared
frame's) and every other robot that has sent frames are that far; a robot whose camera starts later (named at the
start, or added with ``add_camera``) joins the running system once its own first frames are in. While the first
robot has sent no frame, the others' frames are held for it until one that is that far holds
``fleet.START_WAIT_FRAMES``: the run then starts with those that are that far (the first of them takes the
shared frame), and the first robot joins when its frames come, as a late camera (a warning says so). Held frames run
in the order they came, and from then on every ``add_frame`` of a running robot runs its frame at once and returns
its pose. Frames given in the order ``run`` would take them (``data.interleave``: by time) give the same results as
``run`` on the recorded sequences, file for file, where the depth is measured (a network's depth, scaled to the
camera height, is scaled from the frames seen so far, not from frames spread over the whole sequence). A frame the
pipeline has run is dropped (the robot's ``FrameStream`` holds only what is still to be run).

``finish`` ends the run (the final whole-graph matching, the results folder, the summary); leaving a ``with`` block
finishes it too, as stopped (no final matching) on a Ctrl-C or ``sys.exit``; an error raised in the block writes
every keyframe so far into the folder as a checkpoint and marks it incomplete. A Ctrl-C between the held frames a
call runs leaves the rest held, run in order at the robot's next frame or ``finish``.

``LiveRobot`` is one robot fed the same way in its own process, for a map server elsewhere (``shgm-slam server``,
Eclipse Zenoh): ``shgm-slam robot`` on a camera that is driving now.
"""

from shgm_slam.live.fleet import LiveRun
from shgm_slam.live.frames import LivePose, Warmup
from shgm_slam.live.robot import LiveRobot

__all__ = ["LivePose", "LiveRobot", "LiveRun", "Warmup"]
