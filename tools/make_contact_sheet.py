"""Render docs/contact_sheet.png: the airsim-like scenario at a glance (it is shown in the README).

Top: a bird's-eye render of the city with the robots' tracks (car1 red, car2 yellow, uav magenta) and
the same view in Cityscapes label colours. Below: a few frames per robot, each as RGB | depth (turbo,
0-80 m, black = invalid) | labels.

    .venv/bin/python tools/make_contact_sheet.py [--out docs/contact_sheet.png] [--seed 0]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from shgm_slam.geometry.camera import project
from shgm_slam.geometry.se3 import inverse, transform_points
from shgm_slam.labels import colorize_labels
from shgm_slam.sim.render import Lighting, Renderer, make_intrinsics
from shgm_slam.sim.scenarios import ScenarioOptions, build_scenario
from shgm_slam.sim.trajectories import camera_poses

TRACK_BGR = {"car1": (40, 40, 230), "car2": (0, 215, 255), "uav": (230, 40, 230)}


def depth_image(depth_m: np.ndarray, far_m: float = 80.0) -> np.ndarray:
    """(H, W, 3) uint8 RGB turbo colouring of depth (near blue, far red), black where invalid."""
    d8 = (np.clip(depth_m / far_m, 0, 1) * 255).astype(np.uint8)
    rgb = cv2.applyColorMap(d8, cv2.COLORMAP_TURBO)[..., ::-1].copy()
    rgb[depth_m <= 0] = 0
    return rgb


def caption(image_rgb: np.ndarray, text: str) -> np.ndarray:
    out = image_rgb.copy()
    for colour, thick in (((0, 0, 0), 3), ((255, 255, 255), 1)):
        cv2.putText(out, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, colour, thick, cv2.LINE_AA)
    return out


def birds_eye(plan, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Top-down RGB and label renders over all tracks with the tracks drawn in."""
    xy = np.concatenate([r.positions_xyz[:, :2] for r in plan.robots])
    centre = 0.5 * (xy.min(0) + xy.max(0))
    span_x, span_y = xy.max(0) - xy.min(0) + 120.0
    K = make_intrinsics(width, height, hfov_deg=50.0)
    altitude = max(span_x, span_y * width / height) / (2 * np.tan(np.radians(25.0)))  # image x = east
    T = camera_poses(np.array([[*centre, altitude]]), np.array([[0.0, 1.0, 0.0]]), np.pi / 2)[0]
    no_haze = Lighting(fog_distance_m=1e9, shadow_range_m=1e9)
    with Renderer(plan.world, K, max_depth_m=5000.0, lighting=no_haze) as renderer:
        view = renderer.render(T)
    rgb, lab = view.image_rgb.copy(), colorize_labels(view.label_ids)
    for width_px, r in zip(
        (7, 4, 2), reversed(plan.robots), strict=False
    ):  # uav wide below, car1 thin on top
        uv, ok = project(transform_points(inverse(T), r.positions_xyz), K)
        pts = uv[ok].round().astype(np.int32)
        for img in (rgb, lab):
            cv2.polylines(
                img, [pts], False, TRACK_BGR.get(r.name, (255, 255, 255))[::-1], width_px, cv2.LINE_AA
            )
            cv2.circle(img, tuple(int(v) for v in pts[0]), 4, (255, 255, 255), -1, cv2.LINE_AA)
    return caption(rgb, "bird's eye: car1 red, car2 yellow, uav magenta (dot = start)"), caption(
        lab, "labels"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/contact_sheet.png"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=192)
    parser.add_argument(
        "--frames", type=float, nargs="+", default=[0.25, 0.7], help="positions along each track"
    )
    args = parser.parse_args()
    plan = build_scenario("airsim-like", ScenarioOptions(seed=args.seed))
    W, H = args.width, args.height
    rows = []
    top_rgb, top_lab = birds_eye(plan, 3 * W // 2, 8 * H // 5)
    rows.append(np.concatenate([top_rgb, top_lab], 1))
    with Renderer(plan.world, make_intrinsics(W, H)) as renderer:
        for r in plan.robots:
            for f in args.frames:
                k = int(f * (len(r) - 1))
                view = renderer.render(r.T_world_cam[k])
                rows.append(
                    np.concatenate(
                        [
                            caption(view.image_rgb, f"{r.name} frame {k}  t={r.timestamps_s[k]:.1f} s"),
                            caption(depth_image(view.depth_m), "depth 0-80 m"),
                            caption(colorize_labels(view.label_ids), "labels (Cityscapes train ids)"),
                        ],
                        1,
                    )
                )
    sheet = np.concatenate(rows, 0)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), sheet[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]}, {args.out.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
