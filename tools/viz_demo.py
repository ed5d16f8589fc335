"""Write a small synthetic multi-robot recording through ``RerunLogger`` and measure the logging cost.

Robots drive around one rounded-rectangle block of a toy city (camera RDF frame, ground at y = +1.65 m);
their odometry drifts in yaw, the "fused" trajectory is the true one; objects along the block form
the semantic graphs; one robot pair gets an accepted match, another a rejected one. Used to check
the default blueprint (``tools/screenshot_rrd.sh``) and to measure logging cost per frame.

    .venv/bin/python tools/viz_demo.py /tmp/viz_demo.rrd --robots 3 --frames 40
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from shgm_slam.geometry.camera import backproject
from shgm_slam.geometry.se3 import make_pose, rot_y, transform_points
from shgm_slam.labels import Label, colorize_labels
from shgm_slam.types import GraphArrays, Intrinsics
from shgm_slam.viz.rerun_logger import LogLevel, RerunLogger, RerunMode, make_viz

CAMERA_HEIGHT_M = 1.65
INTR = Intrinsics(fx=360.0, fy=360.0, cx=319.5, cy=95.5, width=640, height=192)


def loop_xz(s_m: np.ndarray, length_m: float = 120.0, width_m: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 3) and headings (N,) rad along a rectangle block, arc length ``s_m`` metres."""
    perimeter = 2 * (length_m + width_m)
    s = np.mod(s_m, perimeter)
    corners = np.array([[0, 0], [0, length_m], [width_m, length_m], [width_m, 0], [0, 0]], dtype=float)
    seg = np.cumsum([0, length_m, width_m, length_m, width_m])
    k = np.clip(np.searchsorted(seg, s, side="right") - 1, 0, 3)
    t = (s - seg[k]) / np.diff(seg)[k]
    xz = corners[k] + t[:, None] * (corners[k + 1] - corners[k])
    d = corners[k + 1] - corners[k]
    heading = np.arctan2(d[:, 0], d[:, 1])
    return np.stack([xz[:, 0], np.zeros_like(s), xz[:, 1]], axis=1), heading


def city_objects(rng: np.random.Generator) -> GraphArrays:
    """Objects on both sides of the block: buildings, poles, vegetation, cars, signs (world frame)."""
    s = np.arange(0.0, 360.0, 7.0)
    xyz, heading = loop_xz(s)
    side = np.where(np.arange(s.size) % 2 == 0, 1.0, -1.0)
    normal = np.stack([np.cos(heading), np.zeros_like(s), -np.sin(heading)], axis=1)
    labels = rng.choice([Label.BUILDING, Label.POLE, Label.VEGETATION, Label.CAR, Label.TRAFFIC_SIGN], s.size)
    height = {Label.BUILDING: -4.0, Label.POLE: -1.0, Label.VEGETATION: -1.5, Label.CAR: 0.9,
              Label.TRAFFIC_SIGN: -1.2}  # fmt: skip
    offset = np.where(labels == Label.BUILDING, 10.0, 5.0)
    pos = xyz + (side * offset)[:, None] * normal
    pos[:, 1] = [height[int(lab)] for lab in labels]
    sizes = np.where(labels == Label.BUILDING, 40_000.0, rng.uniform(2_000, 12_000, s.size))
    return GraphArrays(np.arange(s.size), labels.astype(np.int64), pos, sizes)


def synthetic_images(rng: np.random.Generator, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(H, W, 3) RGB, (H, W) depth m, (H, W) labels of a street view (sky, buildings, road, a car)."""
    H, W = INTR.height, INTR.width
    v = np.arange(H)[:, None] * np.ones((1, W))
    u = np.ones((H, 1)) * np.arange(W)[None, :]
    labels = np.full((H, W), Label.BUILDING, np.uint8)
    labels[v < 40 + 10 * np.sin(u / 50 + frame / 5)] = Label.SKY
    ground = v > INTR.cy + 4
    labels[ground] = Label.ROAD
    labels[ground & (np.abs(u - INTR.cx) > 0.9 * (v - INTR.cy) + 150)] = Label.SIDEWALK
    labels[(np.mod(u + 13 * frame, 160) < 6) & ~ground] = Label.POLE
    labels[(np.mod(u + 7 * frame, 230) < 40) & (v > 60) & ~ground] = Label.VEGETATION
    car = (np.abs(u - 420 - 30 * np.sin(frame / 7)) < 50) & (v > 85) & (v < 125)
    labels[car] = Label.CAR
    depth = np.full((H, W), 18.0, np.float32)
    depth[ground] = (INTR.fy * CAMERA_HEIGHT_M / np.maximum(v - INTR.cy, 1.0))[ground]
    depth[car] = 9.0
    depth[labels == Label.SKY] = 0.0
    depth = np.minimum(depth, 60.0)
    rgb = colorize_labels(labels).astype(np.int16) + rng.integers(-20, 21, (H, W, 3))
    return np.clip(rgb, 0, 255).astype(np.uint8), depth, labels


def run(out: Path, num_robots: int, num_frames: int, seed: int = 0) -> dict[str, float]:
    """Log the demo to ``out``; returns measured costs (ms per frame, bytes per frame)."""
    rng = np.random.default_rng(seed)
    robots = [f"robot_{chr(ord('a') + i)}" for i in range(num_robots)]
    viz = make_viz(RerunMode.SAVE, robots=robots, save_path=out)
    assert isinstance(viz, RerunLogger)
    viz.setup(dict.fromkeys(robots, INTR))
    world = city_objects(rng)
    starts = np.arange(num_robots) * 110.0
    speed = 1.5
    frame_ms: list[float] = []
    for k in range(num_frames):
        for i, robot in enumerate(robots):
            s = starts[i] + speed * np.arange(k + 1)
            xyz, heading = loop_xz(s)
            drift = 0.004 * np.arange(k + 1) * (1 + i)  # yaw drift of odometry, rad
            step_xyz = np.stack([np.sin(heading + drift), np.zeros(k + 1), np.cos(heading + drift)], 1)
            odo_xyz = xyz[0] + np.cumsum(step_xyz * speed, axis=0)
            T_shared_cam = make_pose(rot_y(heading[-1]), xyz[-1])
            rgb, depth, labels = synthetic_images(rng, k + 7 * i)
            pts_cam, pix = backproject(depth, INTR, stride=1)
            pts = transform_points(T_shared_cam, pts_cam)
            viz.set_time(robot, k, 0.1 * k)
            t0 = time.perf_counter()
            viz.log_frame(robot, T_shared_cam, rgb, depth, labels, pts, labels.reshape(-1)[pix])
            frame_ms.append((time.perf_counter() - t0) * 1e3)
            viz.log_timings(
                robot,
                {
                    "perception": rng.uniform(30, 40),
                    "odometry": rng.uniform(15, 25),
                    "graph": rng.uniform(5, 10),
                    "server": rng.uniform(1, 3),
                },
            )
            if k % 5 == 0 or k == num_frames - 1:
                seen = np.linalg.norm(world.positions_xyz[:, [0, 2]][:, None] - xyz[None, :, [0, 2]], axis=2)
                graph = world.subset(seen.min(axis=1) < 25.0)
                d = np.linalg.norm(graph.positions_xyz[:, None] - graph.positions_xyz[None], axis=2)
                ii, jj = np.nonzero(np.triu(d < 15.0, 1))
                graph.edges = np.stack([ii, jj], axis=1)
                viz.log_graph(robot, graph)
                viz.log_trajectories(robot, odo_xyz, xyz)
        if k == num_frames // 2 and num_robots > 1:
            a = world.positions_xyz[:6]
            b = a + np.array([1.5, -8.0, 2.0])  # robot_b's nodes before the correction
            viz.log_matches(robots[0], robots[1], a, b, True, 6, 0.82)
            viz.log_text(f"{robots[0]}<->{robots[1]}: 6 inliers, accepted", LogLevel.INFO)
        if k == num_frames - 1 and num_robots > 2:
            a = world.positions_xyz[rng.choice(len(world), 5, replace=False)]
            b = world.positions_xyz[rng.choice(len(world), 5, replace=False)]
            viz.log_matches(robots[1], robots[2], a, b, False, 2, 0.41)
            viz.log_text(f"{robots[1]}<->{robots[2]}: 2 inliers, rejected", LogLevel.WARN)
        viz.log_scalar("closures_accepted", float(k >= num_frames // 2))
    viz.close()
    n = num_frames * num_robots
    return {
        "frames": n,
        "log_frame_ms_mean": float(np.mean(frame_ms)),
        "log_frame_ms_median": float(np.median(frame_ms)),
        "rrd_bytes_per_frame": out.stat().st_size / n,
    }


def bench_log_frame(out: Path, num_frames: int = 50, image_dir: Path | None = None) -> dict[str, float]:
    """Cost of ``log_frame`` for a 640x192 frame (JPEG RGB, depth, labels) + a 20k-point cloud.

    Every frame has new content (identical frames would compress away in the .rrd): the synthetic
    street moves, its depth is modulated smoothly, and with ``image_dir`` (PNG frames, e.g. KITTI
    ``image_0``, resized to 640x192) the RGB is real. Returns ms per call and .rrd bytes per frame.
    """
    import cv2

    rng = np.random.default_rng(0)
    pngs = sorted(image_dir.glob("*.png")) if image_dir is not None else []
    viz = make_viz(RerunMode.SAVE, robots=["robot_a"], save_path=out)
    viz.setup({"robot_a": INTR})
    ms = []
    for k in range(num_frames):
        rgb, depth, labels = synthetic_images(rng, k)
        depth = depth * (1.0 + 0.05 * np.sin(np.arange(INTR.width) / 40.0 + k)).astype(np.float32)
        if pngs:
            img = cv2.imread(str(pngs[k % len(pngs)]), cv2.IMREAD_COLOR)
            rgb = cv2.resize(img, INTR.size_wh, interpolation=cv2.INTER_AREA)[:, :, ::-1].copy()
        pts_cam, pix = backproject(depth, INTR)
        keep = rng.choice(pts_cam.shape[0], 20_000, replace=False)
        T = make_pose(rot_y(0.01 * k), np.array([0.0, 0.0, 1.0 * k]))
        pts, pts_labels = transform_points(T, pts_cam[keep]), labels.reshape(-1)[pix[keep]]
        viz.set_time("robot_a", k, 0.1 * k)
        t0 = time.perf_counter()
        viz.log_frame("robot_a", T, rgb, depth, labels, pts, pts_labels)
        ms.append((time.perf_counter() - t0) * 1e3)
    viz.close()
    return {
        "frames": num_frames,
        "log_frame_ms_median": float(np.median(ms)),
        "log_frame_ms_mean": float(np.mean(ms)),
        "rrd_bytes_per_frame": out.stat().st_size / num_frames,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--robots", type=int, default=3)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--bench", action="store_true", help="measure log_frame (640x192 + 20k points) only")
    parser.add_argument("--image-dir", type=Path, default=None, help="PNG frames for --bench (KITTI image_0)")
    args = parser.parse_args()
    if args.bench:
        print(bench_log_frame(args.out, args.frames, args.image_dir))
    else:
        print(run(args.out, args.robots, args.frames))


if __name__ == "__main__":
    main()
