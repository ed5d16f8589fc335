"""The held-out benchmark's summary: rates per input mode and scenario, the worst cases, and the tables the
README shows (``heldout_markdown``), from the robots' verdicts (``heldout_judge``) and the runs' judged matches."""

from __future__ import annotations

import numpy as np

from shgm_slam.bench.heldout_judge import GROSS_ERROR_M, PLACED_RIGHT_M, InputMode, Outcome


def summarize(rows: list[dict], runs: list[dict] | None = None) -> dict:
    """Rates per mode and per (mode, scenario): placed right, wrong (false merges), not placed, odometry;
    with ``runs`` (their ``matches`` entries), the accepted matches and how many were off at their place."""

    def tol(r: dict) -> float:
        return PLACED_RIGHT_M[InputMode(r["mode"])]

    def stats(sel: list[dict]) -> dict:
        refs = [r for r in sel if r["reference"]]
        ovl = [r for r in sel if r["overlaps"] and not r["reference"]]
        apart = [r for r in sel if not r["overlaps"] and not r["reference"]]
        right = sum(r["outcome"] == Outcome.RIGHT.value for r in ovl)
        return {
            "robot_worlds": len(sel),
            "overlapping": len(ovl),
            "placed_right": right,
            "placed_right_rate": right / len(ovl) if ovl else float("nan"),
            "fused_within": sum(r["outcome"] != Outcome.NOT_PLACED.value and r["ate_fused_m"] <= tol(r) for r in ovl),
            "fused_within_unaligned": sum(
                r["outcome"] != Outcome.NOT_PLACED.value and r["ate_fused_raw_m"] <= tol(r) for r in ovl
            ),
            "wrong": sum(r["outcome"] == Outcome.WRONG.value for r in ovl + apart),
            "wrong_gross": sum(
                r["outcome"] == Outcome.WRONG.value and not r["placement_error_m"] <= GROSS_ERROR_M for r in ovl + apart
            ),
            "wrong_gross_provisional": sum(
                r["outcome"] == Outcome.WRONG.value
                and not r["placement_error_m"] <= GROSS_ERROR_M
                and bool(r.get("provisional"))
                for r in ovl + apart
            ),
            "not_placed": sum(r["outcome"] == Outcome.NOT_PLACED.value for r in ovl),
            "not_placed_waiting": sum(r["outcome"] == Outcome.NOT_PLACED.value and bool(r.get("waiting")) for r in ovl),
            "references": len(refs),
            "references_within": sum(r["outcome"] == Outcome.RIGHT.value for r in refs),
            "apart_kept_apart": sum(r["outcome"] == Outcome.RIGHT.value for r in apart),
            "apart": len(apart),
            "failures_detected": sum(r["failures_detected"] for r in sel),
            "robots_with_failures_detected": sum(r["failures_detected"] > 0 for r in sel),
            "undetected_breaks": sum(r["odometry_breaks"] for r in sel),
            "robots_with_undetected_breaks": sum(r["odometry_breaks"] > 0 for r in sel),
            "median_ate_right_m": float(np.median([r["ate_fused_m"] for r in ovl if r["outcome"] == "right"]))
            if right
            else float("nan"),
        }

    def match_stats(mode: str, scenario: str | None) -> dict:
        judged = [r["matches"] for r in runs or [] if r["mode"] == mode and "matches" in r
                  and scenario in (None, r["scenario"])]  # fmt: skip
        return {
            "matches_accepted": sum(m["accepted"] for m in judged),
            "matches_off": sum(m["off"] for m in judged),
            "matches_gross": sum(m["gross"] for m in judged),
            "anchorings": sum(m.get("anchorings") or 0 for m in judged),
            "anchorings_gross": sum(m.get("anchorings_gross", 0) for m in judged),
            "anchorings_gross_confirmed": sum(m.get("anchorings_gross_confirmed", 0) for m in judged),
            "anchorings_unrecorded": sum(m.get("anchorings") is None for m in judged),
            "rejected": sum(m.get("rejected") or 0 for m in judged),
            "rejected_right": sum(m.get("rejected_right", 0) for m in judged),
            "rejected_unrecorded": sum(m.get("rejected") is None for m in judged),
        }

    out: dict = {}
    for mode in sorted({r["mode"] for r in rows}):
        sel = [r for r in rows if r["mode"] == mode]
        out[mode] = {"all": stats(sel) | match_stats(mode, None)}
        for scenario in sorted({r["scenario"] for r in sel}):
            out[mode][scenario] = stats([r for r in sel if r["scenario"] == scenario]) | match_stats(mode, scenario)
        bad = [r for r in sel if r["outcome"] != Outcome.RIGHT.value]
        bad.sort(
            key=lambda r: (
                r["reference"],
                r["outcome"] != Outcome.WRONG.value,
                -np.nan_to_num(r["placement_error_m"]),
                -np.nan_to_num(r["ate_fused_m"]),
            )
        )
        out[mode]["worst"] = [
            {
                k: r[k]
                for k in (
                    "scenario",
                    "seed",
                    "robot",
                    "reference",
                    "outcome",
                    "placement_error_m",
                    "ate_fused_m",
                    "placed_fraction",
                    "notes",
                )
            }
            for r in bad[:8]
        ]
    return out


def heldout_markdown(results: dict) -> str:
    """The held-out tables as markdown (what the README shows)."""
    o = results["options"]
    stopped = (
        f"**Interrupted**: only the {len(results.get('runs', []))} runs finished before the stop are counted; "
        "the same command resumes the rest.\n\n"
        if results.get("interrupted")
        else ""
    )
    lines = [
        stopped + f"Seeds {o['seeds'][0]}-{o['seeds'][-1]} ({len(o['seeds'])} worlds per scenario), "
        f"{o['resolution'][0]}x{o['resolution'][1]}"
        + (f" ({o['supersample']}x{o['supersample']} rays per pixel)" if o.get("supersample", 1) > 1 else "")
        + (f" at {o['fps']:g} Hz" if o.get("fps", 10.0) != 10.0 else "")
        + (
            f", airsim-like UAVs at {o['uav_altitude_m'][0]:g}-{o['uav_altitude_m'][1]:g} m"
            if o.get("uav_altitude_m")
            else ""
        )
        + (
            f", rendered frames corrupted (depth noise {o['depth_noise']:g}, label noise {o['label_noise']:g})"
            if o.get("depth_noise") or o.get("label_noise")
            else ""
        )
        + ", default configuration; tuning seeds "
        f"{o['tuning_seeds'][0]}-{o['tuning_seeds'][-1]}. Placed right: placed within "
        + ", ".join(f"{v:g} m ({k})" for k, v in o["placed_right_m"].items())
        + ": the rigid transform that best lays its fused trajectory onto the truth moves it less than that "
        "(placement, not its own drift). 'Fused ATE within': its fused ATE in the shared frame within the "
        "same tolerance once the shared frame's gauge is fixed by the reference robot's trajectory (one rigid "
        "transform for all robots); '(unaligned)': with no alignment at all. 'Accepted matches off': the map "
        "server's accepted graph matches whose transform, read at the two keyframes it joins, is farther from "
        "the truth than the same tolerance (> 20 m: an alias); a robot placed wrong whose matches were all "
        "right at their place was bent away by its own drift, not merged by a false match. 'Placed through "
        "a false closure': times a robot entered the shared frame through a closure more than 20 m off at its "
        "place, of all times a robot entered it, even if later matches withdrew it (a false merge the final "
        "trajectories no longer show); in brackets those the server ever confirmed (two independent matches "
        "agreeing), the rest stayed provisional and were reported so; '?' where the run predates that record. "
        "'Not placed': in brackets those 'waiting', whose accepted matches were fewer independent pieces of "
        "evidence than a robot needs to enter the shared frame. "
        "'Rejected matches right': matches the verification rejected whose best hypothesis, read at B's newest "
        "keyframe, was within the tolerance anyway (right alignments missed), of all rejected matches with a "
        "hypothesis.",
        "",
        "| input | scenario | robot-worlds | overlapping placed right | fused ATE within | (unaligned) | wrong |"
        " of which > 20 m | not placed |"
        " disjoint kept apart | reference within | odometry failures detected (robots) |"
        " undetected breaks (robots) | median ATE right m | accepted matches off (> 20 m) |"
        " placed through a false closure (confirmed) | rejected matches right |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for mode, per in results["summary"].items():
        for scenario, s in per.items():
            if scenario == "worst":
                continue
            rate = f"{s['placed_right']}/{s['overlapping']}" + (
                f" ({100 * s['placed_right_rate']:.0f} %)" if s["overlapping"] else ""
            )
            lines.append(
                f"| {mode} | {'**all**' if scenario == 'all' else scenario} | {s['robot_worlds']} | {rate} | "
                f"{s['fused_within']} | {s['fused_within_unaligned']} | {s['wrong']} | {s['wrong_gross']}"
                + (f" ({s['wrong_gross_provisional']} provisional)" if s.get("wrong_gross_provisional") else "")
                + " | "
                f"{s['not_placed']}"
                + (f" ({s['not_placed_waiting']} waiting)" if s.get("not_placed_waiting") else "")
                + " | "
                f"{s['apart_kept_apart']}/{s['apart']} | "
                f"{s['references_within']}/{s['references']} | "
                f"{s['failures_detected']} ({s['robots_with_failures_detected']}) | "
                f"{s['undetected_breaks']} ({s['robots_with_undetected_breaks']}) | "
                f"{s['median_ate_right_m']:.2f} | "
                f"{s.get('matches_off', 0)}/{s.get('matches_accepted', 0)} ({s.get('matches_gross', 0)}) | "
                + (
                    "?"
                    if s.get("anchorings_unrecorded")
                    else f"{s.get('anchorings_gross', 0)}/{s.get('anchorings')} "
                    f"({s.get('anchorings_gross_confirmed', 0)})"
                )
                + " | "
                + ("?" if s.get("rejected_unrecorded") else f"{s.get('rejected_right', 0)}/{s.get('rejected', 0)}")
                + " |"
            )
    if results.get("skipped_worlds"):
        lines += ["", "Worlds skipped (not built as asked; not in the tables):", ""]
        lines += [f"- {w['scenario']} seed {w['seed']}: {w['skipped']}" for w in results["skipped_worlds"]]
    for mode, per in results["summary"].items():
        if per["worst"]:
            lines += ["", f"Worst cases ({mode}):", ""]
            for w in per["worst"]:
                note = "; ".join(w["notes"])
                lines.append(
                    f"- {w['scenario']} seed {w['seed']} {w['robot']}{' (reference)' if w['reference'] else ''}: "
                    f"{w['outcome']}, placement {w['placement_error_m']:.1f} m, fused ATE "
                    f"{w['ate_fused_m']:.1f} m, {w['placed_fraction']:.0%} placed" + (f" ({note})" if note else "")
                )
    return "\n".join(lines) + "\n"
