"""The accepted alignment's last step: a robust refit on every partner near it (Tukey's biweight).

The hypotheses are refined and judged on partners within ``verification_radius_m``: a hard gate. On a
sparse map with noisy centroids (0.5-2 m) that gate keeps a few wrong partners (another pole 2.5 m away)
and drops right ones whose centroids landed farther than the radius; both pull the yaw. Over a short
shared street a degree of yaw is metres at the far end of B's graph (a 1.6 deg error is 3.8 m at 140 m),
so most of the near-miss claims of the sparse benchmark were right at the overlap and wrong by their yaw.

Once an alignment is accepted (nothing here changes a decision: the evidence is judged on the alignment
the search found), its transform is refitted by iteratively reweighted least squares: partners within
``GATE_RADII`` verification radii, each weighted by Tukey's biweight of its distance alone, with the cutoff
``TUKEY_C`` times the median partner distance (the data's own scale). Chosen on the sparse tuning seeds
10-39 and 50-59 (4-DoF and 6-DoF; held-out notes in docs/benchmarks.md): against the hard-gate fit, median
error at B's centroid 0.47 -> 0.40 m (4-DoF) and 0.50 -> 0.43 m (6-DoF), the farthest accepted match
5.5 -> 3.0 m and 6.0 -> 3.3 m; a gate of 1.5 or 2.5 radii, or a Cauchy weight, measured within a few
centimetres of it.

No size weights (Eq. 2's, ``matching.weighted_pose``): they favour the largest objects, buildings and
ground, whose centroids depend on the part each robot saw. On the map server's replays of four rendered
held-out worlds (airsim-like and synthia-like, seeds 500-501) the accepted matches more than 2 m off at
their keyframes were 118 of 371 with the hard-gate fit alone, 167 with a size-weighted polish and 80 with
this one; on the held-out tuning worlds 10-13 (all four scenarios) 152, 255 and 103 of 776.

Pure function of arrays.
"""

from __future__ import annotations

import numpy as np

from shgm_slam.geometry.se3 import transform_points
from shgm_slam.matching.labelled_tree import LabelledTree
from shgm_slam.matching.pose import fit_pose
from shgm_slam.matching.verification import partner_pairs
from shgm_slam.types import GraphArrays

GATE_RADII = 2.0
"""Partners are searched within this many ``verification_radius_m`` of the alignment."""
TUKEY_C = 4.685
"""Tukey's biweight cutoff in units of the median partner distance: a partner farther gets no weight."""
MIN_SCALE_M = 0.2
"""The median partner distance used for the cutoff is at least this (exact maps: the fit stays a fit)."""
ITERATIONS = 10
"""Reweighting steps at most; stops earlier when a step moves none of B's nodes by ``TOLERANCE_M`` or more
(3-4 steps on the sparse tuning pairs, ~0.5 ms each)."""
TOLERANCE_M = 0.01
MIN_PARTNERS = 3
"""Fewer weighted partners leave the alignment as it was."""


def biweight(distances_m: np.ndarray) -> np.ndarray:
    """(K,) Tukey biweights of (K,) partner distances in metres: ``(1 - (d / c)^2)^2`` below the cutoff
    ``c = TUKEY_C * max(median distance, MIN_SCALE_M)``, 0 beyond it."""
    d = np.asarray(distances_m, dtype=np.float64)
    if d.size == 0:
        return d
    c = TUKEY_C * max(float(np.median(d)), MIN_SCALE_M)
    return np.where(d < c, (1.0 - (d / c) ** 2) ** 2, 0.0)


def polish_alignment(
    T_a_b: np.ndarray,
    a: GraphArrays,
    b: GraphArrays,
    tree_a: LabelledTree,
    radius_m: float,
    *,
    gravity_aligned: bool,
    up: np.ndarray,
) -> np.ndarray:
    """Refit an accepted (4, 4) ``T_a_b`` (B's frame -> A's, metres) robustly on its nearby partners.

    Args:
        T_a_b: the alignment the search found and the verification accepted.
        a, b: the two graphs (positions in each robot's frame, metres).
        tree_a: ``LabelledTree`` of A's nodes.
        radius_m: the verification radius; partners are searched within ``GATE_RADII`` of it.
        gravity_aligned: fit a yaw about ``up`` (3,) only (4-DoF), else the full rotation.

    Returns:
        (4, 4) float64 the refitted ``T_a_b``; the given one when fewer than ``MIN_PARTNERS`` partners carry
        weight, or when the refit would move its partners' centroid farther than ``radius_m`` (the alignment
        that was judged is kept rather than one nobody judged; far from the overlap a corrected yaw may
        move B's nodes by more, which is the point).
    """
    T0 = np.asarray(T_a_b, dtype=np.float64)
    T = T0.copy()
    gate = GATE_RADII * radius_m
    centre_b = None
    mapped = transform_points(T, b.positions_xyz)
    for _ in range(ITERATIONS):
        pairs, dist = partner_pairs(tree_a, mapped, b.label_ids, gate)
        w = biweight(dist)
        keep = w > 0
        if np.count_nonzero(keep) < MIN_PARTNERS:
            break
        rows_a, rows_b = pairs[keep, 0], pairs[keep, 1]
        centre_b = b.positions_xyz[rows_b].mean(axis=0, keepdims=True)
        T = fit_pose(b.positions_xyz[rows_b], a.positions_xyz[rows_a], w[keep], gravity_aligned, up)
        mapped, before = transform_points(T, b.positions_xyz), mapped  # B under the new fit: the next partners
        moved = float(np.max(np.linalg.norm(mapped - before, axis=1)))
        if moved < TOLERANCE_M:
            break
    if centre_b is None or not np.all(np.isfinite(T)):
        return T0
    if np.linalg.norm(transform_points(T, centre_b) - transform_points(T0, centre_b)) > radius_m:
        return T0
    return T
