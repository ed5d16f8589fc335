"""Markdown tables and the precision-recall plot of ``run_localization_benchmark`` results."""

from __future__ import annotations

from pathlib import Path

PAPER_TABLE2 = {
    ("car-car", "random-walk"): "4.155 s, 125 good (40.0 %), 3.44 ± 1.39 m, 0.92 ± 0.49°",
    ("car-car", "neighbor-vector"): "0.013 s, 120 good (37.8 %), 4.55 ± 1.32 m, 0.48 ± 0.31°",
    ("car-car", "histogram"): "0.132 s, 152 good (49.1 %), 3.12 ± 0.76 m, 0.30 ± 0.29°",
    ("uav-car", "random-walk"): "6.637 s, 136 good (43.6 %), 2.23 ± 0.88 m, 2.62 ± 0.46°",
    ("uav-car", "neighbor-vector"): "0.021 s, 100 good (31.7 %), 3.23 ± 1.02 m, 3.25 ± 0.54°",
    ("uav-car", "histogram"): "0.195 s, 142 good (45.1 %), 2.12 ± 0.47 m, 2.61 ± 0.25°",
}
"""The paper's Table II (AirSim, i7-8565U) for reference."""

PAPER_FIG5 = {"histogram": 0.95, "neighbor-vector": 0.79, "random-walk": 0.85}
"""Success rates at recall 0.35 in the paper's Fig. 5 (random walk = X-view's result)."""


def _pm(pair: list[float] | None, digits: int = 2) -> str:
    return "–" if pair is None else f"{pair[0]:.{digits}f} ± {pair[1]:.{digits}f}"


def _f(value: float | None, fmt: str = ".3f") -> str:
    return "–" if value is None else format(value, fmt)


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    align = ["---" if i == 0 else "---:" for i in range(len(header))]
    return ["| " + " | ".join(header) + " |", "| " + " | ".join(align) + " |",
            *["| " + " | ".join(r) + " |" for r in rows]]


def table2_markdown(results: dict) -> list[str]:
    rows = []
    for r in results["table2"]:
        xv = r.get("xview_per_pair")
        total = f"{r['total_ms_mean']:.1f}"
        if xv:
            total += f" (X-view per pair: {xv['end_to_end_ms']:.0f})"
        rows.append([
            r["pair"], f"{r['nodes_a']} / {r['nodes_b']}", r["descriptor"], r["mode"], f"{r['matching_ms_mean']:.2f}",
            f"{r['good_matches']:.0f} / {r['best_candidates']:.0f}", f"{100 * r['good_match_rate']:.1f}", total,
            f"{r['successes']}/{r['queries']}", str(r["false_successes"]), _pm(r["trans_err_m"]),
            _pm(r["rot_err_deg"]),
        ])  # fmt: skip
    out = [
        "### Table II: whole-graph matching on airsim-like (mean over runs with random transforms and seeds)",
        "",
        *_table(["robots", "nodes A / B", "descriptor", "mode", "descr.+match ms", "good matches",
                 "good %", "total ms", "success", "false", "trans. err m", "rot. err °"], rows),
        "",
        "Good matches: the best-scoring node of A for each node of B (score > threshold), within 10 m under "
        "the ground truth (paper's definition); errors of the accepted matches, translation at B's centroid.",
        "Paper (AirSim, i7-8565U): " + "; ".join(f"{p} {k}: {v}" for (p, k), v in PAPER_TABLE2.items()) + ".",
    ]
    return out


def figure5_markdown(results: dict) -> list[str]:
    rows = []
    for r in results["figure5"]:
        pr, op = r["pr"], r["operating_point"]
        paper = PAPER_FIG5.get(r["descriptor"])
        rows.append([
            r["descriptor"], r["mode"], _f(pr["precision_at_recall"]), _f(pr["best_f1"]),
            _f(pr["max_recall"]), f"{r['successes']}/{r['queries']}", str(r["false_successes"]),
            _f(op["precision"]), _f(op["recall"]), _pm(r["trans_err_m"]), f"{r['total_ms_mean']:.1f}",
            "–" if paper is None else f"{paper:.2f}",
        ])  # fmt: skip
    return [
        f"### Fig. 5: synthia-like, {results['synthia_queries']} backward 30-frame graphs vs the whole forward graph",
        "",
        *_table(["descriptor", "mode", "success @ recall 0.35", "best F1", "max recall", "accepted",
                 "false accepted", "precision (accepted)", "recall (accepted)", "trans. err m", "ms/query",
                 "paper @ 0.35"], rows),
        "",
        "PR over the inlier-count threshold T_r (accept when inliers > T_r): precision = correct accepted / "
        "accepted, recall = correct accepted / all queries, correct = translation error < 20 m. "
        "'accepted' uses the matcher's own success test instead of T_r.",
    ]


def table1_markdown(results: dict) -> list[str]:
    t = results["table1"]
    rows = [[f"graph extraction ({res})", f"{v['mean']:.2f}" + (f" ± {v['std']:.2f}" if "std" in v else ""),
             "per frame"] for res, v in t["extraction_ms_per_frame"].items()]
    rows.append(["graph update (merge + edges)", f"{t['graph_update_ms_per_keyframe']:.3f}", "per keyframe"])
    for key, st in t["per_query_ms"].items():
        if key.startswith("histogram/"):
            mode = key.split("/")[1]
            rows += [[f"{stage} ({mode})", f"{st.get(stage, 0.0):.3f}", "per query"]
                     for stage in ("descriptors", "matching", "ransac", "pose", "total")]
    return ["### Table I: time per module (ms; synthia-like queries: 30-frame graph vs the whole map)", "",
            *_table(["module", "ms", "unit"], rows), "",
            "Paper (i7-8565U, ms/frame): extraction 114.23, descriptors 0.68, matching 1.65, pose 0.63."]


def ablations_markdown(results: dict) -> list[str]:
    rows = [[r["group"], r["variant"] + (" (default)" if r["default"] else ""), r["mode"],
             _f(r["precision_at_recall"]), _f(r["best_f1"]), f"{r['successes']}/{r['queries']}",
             str(r["false_successes"]), _pm(r["trans_err_m"]), f"{r['total_ms_mean']:.1f}"]
            for r in results["ablations"]]  # fmt: skip
    return ["### Fig. 8 ablations (synthia-like, histogram descriptor)", "",
            *_table(["study", "variant", "mode", "success @ recall 0.35", "best F1", "accepted", "false accepted",
                     "trans. err m", "ms/query"], rows)]


def overlap_markdown(results: dict) -> list[str]:
    rows = [[r["descriptor"], r["mode"], r["overlap"], f"{r['successes']}/{r['queries']}",
             str(r["false_successes"]), _pm(r["trans_err_m"])] for r in results["partial_overlap"]]
    return ["### Partial overlap (synthia-like 100-frame sub-maps offset 70-120 frames; airsim-like car1 halves "
            "vs car2), binned by the fraction of B's nodes with a same-label node of A within 5 m", "",
            *_table(["descriptor", "mode", "node overlap", "accepted", "false accepted", "trans. err m"], rows)]


def disjoint_markdown(results: dict) -> list[str]:
    rows = [[r["descriptor"], r["mode"], f"{r['nodes_a']} / {r['nodes_b']}",
             f"{r['whole_successes']}/{r['whole_runs']}", f"{r['window_successes']}/{r['windows']}",
             str(r["max_inliers"])] for r in results["disjoint"]]
    return ["### Disjoint scenario (every success is false)", "",
            *_table(["descriptor", "mode", "nodes A / B", "whole graphs accepted", "30-frame windows accepted",
                     "max inliers"], rows)]


def _value(v) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_value(x)}" for k, x in v.items()) + "}"
    return str(v)


def targets_rows(results: dict) -> list[list[str]]:
    """(target, measured, goal, verdict) rows of the issue's targets."""
    rows = []
    for name, t in results["targets"].items():
        value = {k: v for k, v in t.items() if k not in ("met", "target")}
        rows.append([name, ", ".join(f"{k} {_value(v)}" for k, v in value.items()) or "–", t.get("target", ""),
                     "met" if t["met"] else "NOT met"])
    return rows


def targets_markdown(results: dict) -> list[str]:
    rows = [[*r[:3], "met" if r[3] == "met" else "**NOT met**"] for r in targets_rows(results)]
    return ["### Targets", "", *_table(["target", "measured", "goal", ""], rows)]


def localization_markdown(results: dict) -> str:
    """All tables of the localization benchmark as one markdown document."""
    o = results["options"]
    head = [
        f"## Localization benchmark ({'quick' if o['quick'] else 'full'}: world seed {o['world_seed']}, "
        f"{o['resolution'][0]}x{o['resolution'][1]}, {o['runs']} runs; {results['cpu_count']} cores, "
        f"load {results['load_average_1min_at_start']} at start; {results['wall_time_s']:.0f} s)",
        "",
        "Modes: " + "; ".join(f"{m} = {', '.join(f'{k} {v}' for k, v in ov.items())}"
                              for m, ov in results["mode_overrides"].items()) + ".",
        "",
    ]
    parts = [head, targets_markdown(results), table2_markdown(results), figure5_markdown(results),
             table1_markdown(results), ablations_markdown(results), overlap_markdown(results),
             disjoint_markdown(results)]
    return "\n".join("\n".join(p) + "\n" for p in parts)


def plot_pr_curves(results: dict, path: Path) -> Path:
    """Save the Fig. 5 precision-recall curves of every descriptor and mode as a PNG (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"histogram": "tab:red", "neighbor-vector": "tab:blue", "random-walk": "tab:green"}
    styles = {"paper": "--", "robust": "-"}
    fig, ax = plt.subplots(figsize=(6.0, 4.5), dpi=120)
    for r in results["figure5"]:
        pr = r["pr"]
        label = f"{r['descriptor']} ({r['mode']})"
        ax.plot(pr["recall"], pr["precision"], styles.get(r["mode"], "-"), color=colors.get(r["descriptor"]),
                label=label, drawstyle="steps-post")
        if pr["precision_at_recall"] is not None:
            ax.plot([0.35], [pr["precision_at_recall"]], "o", color=colors.get(r["descriptor"]))
    ax.axvline(0.35, color="0.6", lw=0.8)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.02)
    ax.set_title(f"synthia-like: 30-frame backward graphs vs forward graph ({results['synthia_queries']} queries)")
    ax.title.set_fontsize(9)
    ax.legend(fontsize=7, loc="lower left")
    ax.grid(alpha=0.3)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
