"""Whether two graphs share a vertical axis, read from the graphs themselves (``shgm-slam match --dof auto``).

A map of a city, or a ground robot's graph in a gravity-aligned frame, lies flat: its objects spread over
hundreds of metres horizontally and a few metres vertically, so the direction of least spread of its node
positions is the frame's vertical. When both graphs lie flat along the same coordinate axis, the rotation
between them is a turn about that axis (4-DoF: yaw + translation), and matching them so halves the
rotational freedom a chance alignment has (the sparse benchmark, map-like graphs, report seeds: 83 %
localized gravity-aligned against 78 % in 6-DoF). A graph in a tilted frame (a drone's first camera frame,
a graph turned by an arbitrary rotation) is flat along no coordinate axis and is matched in 6-DoF, as
before.

Only coordinate axes count, and only within ``AXIS_TOLERANCE_DEG``: a map's vertical *is* a coordinate
axis, while a least-spread direction fitted to noisy objects over sloping ground is a few degrees off
(map-like graphs of the sparse benchmark: within 3 degrees); a 4-DoF fit about an axis that is 5 degrees
wrong would put a 100 m graph's far end 9 m too high or low, so a graph tilted more is left to 6-DoF.
"""

from __future__ import annotations

import numpy as np

from shgm_slam.config import Dof, MatchingConfig

FLAT_RATIO = 0.35
"""A graph lies flat when the spread of its nodes along their thinnest principal axis is below this share of
the spread along the middle one (map-like graphs: 0.04-0.26; a street's trees and buildings stand a few
metres high along a street tens of metres wide)."""

AXIS_TOLERANCE_DEG = 5.0
"""The thinnest principal axis must lie within this angle of a coordinate axis (see the module docstring)."""

MIN_FLAT_NODES = 4
"""Fewer nodes say nothing about a plane."""


def flat_axis(positions_xyz: np.ndarray) -> int | None:
    """The coordinate axis (0 = x, 1 = y, 2 = z) along which a graph's nodes lie flat, or None.

    Args:
        positions_xyz: (N, 3) node positions in the graph's frame, metres (finite).

    Returns:
        The index of the coordinate axis within ``AXIS_TOLERANCE_DEG`` of the nodes' thinnest principal
        axis when their spread along it is below ``FLAT_RATIO`` of the middle one; None when the graph
        has fewer than ``MIN_FLAT_NODES`` nodes, is not flat, or is flat along a tilted direction.
    """
    points = np.asarray(positions_xyz, dtype=np.float64).reshape(-1, 3)
    if points.shape[0] < MIN_FLAT_NODES:
        return None
    centred = points - points.mean(axis=0)
    variances, axes = np.linalg.eigh(centred.T @ centred / points.shape[0])  # ascending
    spreads = np.sqrt(np.maximum(variances, 0.0))
    if not spreads[1] > 0 or spreads[0] >= FLAT_RATIO * spreads[1]:
        return None
    normal = axes[:, 0]
    axis = int(np.argmax(np.abs(normal)))
    if abs(normal[axis]) < np.cos(np.radians(AXIS_TOLERANCE_DEG)):
        return None
    return axis


def shared_up_axis(
    positions_a_xyz: np.ndarray, positions_b_xyz: np.ndarray, preferred_up: np.ndarray | None = None
) -> np.ndarray | None:
    """The (3,) unit vertical both graphs lie flat along (``flat_axis``), or None when they do not share one.

    Args:
        positions_a_xyz, positions_b_xyz: (N, 3) and (M, 3) node positions of the two graphs, metres.
        preferred_up: (3,) the configured up axis; when it runs along the shared axis its sign is kept (a
            turn about an axis is the same either way, but results then read as configured).

    Returns:
        (3,) the unit coordinate axis (sign from ``preferred_up`` when parallel, else positive), or None.
    """
    axis_a, axis_b = flat_axis(positions_a_xyz), flat_axis(positions_b_xyz)
    if axis_a is None or axis_a != axis_b:
        return None
    return _signed_axis(axis_a, preferred_up)


def choose_dof(
    dof: Dof, positions_a_xyz: np.ndarray, positions_b_xyz: np.ndarray, cfg: MatchingConfig
) -> tuple[MatchingConfig, str]:
    """The matching configuration for ``dof`` and one line saying what was chosen and why.

    When both graphs lie flat along the same coordinate axis (``shared_up_axis``) that axis becomes the
    ``up_axis`` whatever ``dof`` says: the chance model shifts the hypothesis along the horizontal
    (``chance.shift_vectors``, ``row_steps``), and with the wrong vertical (the KITTI camera frame's
    default -y on a z-up map) it shifted across the street and up into the air instead, found no repeats,
    and let aliases through (the sparse benchmark's map-like graphs, tuning seeds 10-19, 6-DoF: 5 of 100
    far-apart negatives accepted with up -y, none with up +z). Then ``AUTO`` and ``FOUR`` match
    gravity-aligned (yaw + translation) about it, ``SIX`` with any rotation. Without a shared vertical:
    ``AUTO`` does as ``cfg`` says, ``FOUR`` is gravity-aligned about ``cfg.up_axis``, ``SIX`` any rotation.

    Args:
        dof: the requested degrees of freedom.
        positions_a_xyz, positions_b_xyz: (N, 3) and (M, 3) node positions of the two graphs, metres.
        cfg: the configured matching stage (its ``up_axis`` and ``gravity_aligned``).
    """
    axis_a, axis_b = flat_axis(positions_a_xyz), flat_axis(positions_b_xyz)
    if axis_a is not None and axis_a == axis_b:
        up, name = _vertical(axis_a, cfg)
        aligned = dof is not Dof.SIX
        chosen = cfg.model_copy(update={"gravity_aligned": aligned, "up_axis": up})
        if aligned:
            return chosen, f"4-DoF about {name}: both graphs lie flat along it (--dof {dof.value}; 6: any rotation)"
        return chosen, f"6-DoF (--dof 6), vertical {name} for the chance model: both graphs lie flat along it"
    configured = f"4-DoF about matching.up_axis {list(cfg.up_axis)}"
    if dof is Dof.FOUR:
        return cfg.model_copy(update={"gravity_aligned": True}), f"{configured} (--dof 4)"
    if dof is Dof.AUTO and cfg.gravity_aligned:
        return cfg, f"{configured} (the configuration)"
    free = cfg.model_copy(update={"gravity_aligned": False})
    if axis_a is not None:  # the chance model's shifts are taken in A's frame: A's own vertical
        up, name = _vertical(axis_a, cfg)
        chosen = free.model_copy(update={"up_axis": up})
        return chosen, f"6-DoF: B lies flat along no axis that A does (vertical {name} of A for the chance model)"
    how = "(--dof 6)" if dof is Dof.SIX else "(the graphs share no flat vertical axis; --dof 4 for gravity-aligned)"
    return free, f"6-DoF {how}"


def _vertical(axis: int, cfg: MatchingConfig) -> tuple[tuple[float, float, float], str]:
    """Coordinate axis ``axis`` as an ``up_axis`` (signed as ``cfg.up_axis`` where parallel) and its name."""
    up = _signed_axis(axis, np.asarray(cfg.up_axis))
    return (float(up[0]), float(up[1]), float(up[2])), f"{'+' if up[axis] > 0 else '-'}{'xyz'[axis]}"


def _signed_axis(axis: int, preferred_up: np.ndarray | None) -> np.ndarray:
    """(3,) the unit coordinate axis ``axis``, negative when ``preferred_up`` points that way."""
    up = np.zeros(3)
    up[axis] = 1.0
    if preferred_up is not None and float(np.asarray(preferred_up, dtype=np.float64)[axis]) < 0:
        up = -up
    return up
