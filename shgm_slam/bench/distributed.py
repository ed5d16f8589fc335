"""Distributed benchmark (``shgm-slam bench distributed``): the same world run in one process and as a
map server plus one process per robot over Eclipse Zenoh on loopback, with optional faults.

It reports, per run: which robots were placed, each robot's fused ATE in the shared frame (no
alignment) against ground truth, and the traffic: bytes per keyframe, KB/s up and down per robot at
the sequence's frame rate (and at 10 Hz). Faults: a robot killed (SIGKILL) mid-run and started again,
the server killed mid-run and started again. Recovery: the killed server's folder as it was at the
kill, and the no-fault run's whole folder, are recovered twice side by side in this process: from the
newest snapshot plus the journal after it, and from the journal alone (what a server without
snapshots replays).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np

from shgm_slam.bench.report import write_report
from shgm_slam.bench.stopping import run_to_end
from shgm_slam.config import ShgmConfig
from shgm_slam.data import open_sequence
from shgm_slam.errors import ShgmError
from shgm_slam.io.trajectories import read_tum
from shgm_slam.metrics import ate
from shgm_slam.runner import open_robots
from shgm_slam.server.node import QUEUED_FILE, ServerNode
from shgm_slam.transport.inprocess import InProcessBus, InProcessTransport

CLI = [sys.executable, "-m", "shgm_slam"]


class Fault(str, Enum):
    NONE = "none"
    ROBOT = "robot"  # the last robot is killed when the server holds some keyframes, then restarted
    SERVER = "server"  # the server is killed mid-run, then restarted on the same folder


@dataclass
class RunOutcome:
    """One way of running the world."""

    label: str
    placed: dict[str, bool]
    ate_fused_m: dict[str, float]
    wall_s: float
    traffic: dict = field(default_factory=dict)
    recovery: dict = field(default_factory=dict)  # the restarted server's (server.json)
    error: str = ""


@dataclass
class RecoveryTiming:
    """One results folder recovered from its newest snapshot plus the journal after it, and from the journal
    alone, side by side (seconds of wall time each)."""

    label: str
    journal_records: int
    snapshot_records: int
    replayed: int
    snapshot_s: float
    journal_only_s: float
    snapshot_bytes: int = 0  # the newest snapshot file's size


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _gt_shared(robots: dict[str, Path]) -> dict[str, np.ndarray]:
    seqs = {r: open_sequence(str(p)) for r, p in robots.items()}
    ref = next(iter(seqs.values())).gt_poses
    if ref is None or any(s.gt_poses is None for s in seqs.values()):
        raise ShgmError("the distributed benchmark needs ground-truth poses for every robot")
    T0 = np.linalg.inv(ref[0])
    return {r: T0 @ s.gt_poses for r, s in seqs.items()}


def _ate_from_files(out: Path, robot: str, gt_shared: np.ndarray, times: np.ndarray) -> float:
    path = out / f"{robot}_fused_tum.txt"
    if not path.is_file():
        return float("nan")
    t, T = read_tum(path)
    rows = np.searchsorted(times, t)
    ok = (rows < len(times)) & np.isclose(times[np.minimum(rows, len(times) - 1)], t, atol=1e-6)
    if ok.sum() < 3:
        return float("nan")
    return float(ate(gt_shared[rows[ok]], T[ok], align="none")["rmse"])


def _spawn(args: list[str], log_path: Path) -> subprocess.Popen:
    return subprocess.Popen(args, stdout=open(log_path, "w"), stderr=subprocess.STDOUT)


def _wait(p: subprocess.Popen, timeout_s: float, what: str) -> None:
    try:
        p.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        p.kill()
        raise ShgmError(f"{what} did not finish within {timeout_s:.0f} s") from None
    if p.returncode != 0:
        raise ShgmError(f"{what} exited with {p.returncode}")


def _journal_grew(out: Path, nbytes: int, server: subprocess.Popen, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        j = out / "journal.bin"
        if j.is_file() and j.stat().st_size >= nbytes:
            return
        if server.poll() is not None:
            raise ShgmError(f"the server exited early ({server.returncode})")
        time.sleep(0.1)
    raise ShgmError("the server received too little to inject the fault")


def _recovery_files(folder: Path) -> list[Path]:
    """What a restarted map server recovers from: its journal, snapshots and the keyframes still queued."""
    queued = folder / QUEUED_FILE
    return [folder / "journal.bin", *sorted(folder.glob("snapshot-*.bin")), *([queued] if queued.is_file() else [])]


def time_recovery(folder: Path, cfg: ShgmConfig, reference: str, label: str) -> RecoveryTiming:
    """Recover the server state in ``folder`` (its journal and snapshots, copied) twice: with snapshots and
    from the journal alone."""
    times, reports = {}, {}
    for mode, every in (("snapshot", max(cfg.server.snapshot_every_messages, 1)), ("journal", 0)):
        mcfg = cfg.model_copy(update={"server": cfg.server.model_copy(update={"snapshot_every_messages": every})})
        with tempfile.TemporaryDirectory() as tmp:
            for f in _recovery_files(folder):
                shutil.copy2(f, tmp)
            t0 = time.perf_counter()
            node = ServerNode(mcfg, InProcessTransport(InProcessBus()), Path(tmp), reference=reference)
            times[mode], reports[mode] = time.perf_counter() - t0, node.recovery
    r = reports["snapshot"]
    snaps = sorted(folder.glob("snapshot-*.bin"))
    return RecoveryTiming(label, r.snapshot_records + r.replayed, r.snapshot_records, r.replayed, times["snapshot"],
                          times["journal"], snaps[-1].stat().st_size if snaps else 0)  # fmt: skip


def run_distributed(
    robots: dict[str, Path],
    out: Path,
    *,
    fault: Fault = Fault.NONE,
    config: Path | None = None,
    timeout_s: float = 600.0,
) -> RunOutcome:
    """Server + one process per robot on loopback; the server's results are judged against ground truth."""
    out.mkdir(parents=True, exist_ok=True)
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    cfg_args = ["--config", str(config)] if config is not None else []
    names = list(robots)
    server_args = [*CLI, "server", "--out", str(out), "--expect", str(len(names)), "--listen", endpoint,
                   "--reference", names[0], "--rerun", "off", *cfg_args]  # fmt: skip

    def robot(name: str, i: int) -> subprocess.Popen:
        return _spawn([*CLI, "robot", f"{name}={robots[name]}", "--connect", endpoint, "--wait", str(timeout_s),
                       *cfg_args], out / f"{name}.{i}.log")  # fmt: skip

    t0 = time.perf_counter()
    server = _spawn(server_args, out / "server.0.log")
    procs = {n: robot(n, 0) for n in names}
    if fault is Fault.ROBOT:
        _journal_grew(out, 30_000, server, timeout_s)
        victim = names[-1]
        os.kill(procs[victim].pid, signal.SIGKILL)
        procs[victim].wait()
        time.sleep(3.0)  # past the server's name-clash window
        procs[victim] = robot(victim, 1)
    elif fault is Fault.SERVER:
        _journal_grew(out, 300_000, server, timeout_s)  # about half of the demo world's keyframes
        os.kill(server.pid, signal.SIGKILL)
        server.wait()
        at_kill = out / "at-kill"  # the folder as the killed server left it, for time_recovery
        at_kill.mkdir(exist_ok=True)
        for f in _recovery_files(out):
            shutil.copy2(f, at_kill)
        time.sleep(1.0)
        server = _spawn(server_args, out / "server.1.log")
    _wait(server, timeout_s, "the server")
    for n, p in procs.items():
        _wait(p, timeout_s, f"robot {n}")
    wall = time.perf_counter() - t0
    s = json.loads((out / "server.json").read_text())
    gt = _gt_shared(robots)
    times = {r: np.asarray(open_sequence(str(p)).timestamps_s) for r, p in robots.items()}
    return RunOutcome(
        f"server + {len(names)} robot processes" + ("" if fault is Fault.NONE else f", {fault.value} killed"),
        {r: r in s["robots"].get(r, {}).get("placed", []) for r in names},
        {r: _ate_from_files(out, r, gt[r], times[r]) for r in names},
        wall, s["traffic"], s.get("recovery", {}) if fault is Fault.SERVER else {},
    )  # fmt: skip


def run_in_process(robots: dict[str, Path], out: Path, cfg: ShgmConfig) -> RunOutcome:
    """``shgm-slam run`` on the same robots (the in-process bus)."""
    seqs = open_robots([f"{r}={p}" for r, p in robots.items()])
    t0 = time.perf_counter()
    summary = run_to_end(seqs, cfg, out)
    return RunOutcome(
        "shgm-slam run (one process)",
        {r.name: r.localized for r in summary.robots},
        {r.name: r.ate_fused_m for r in summary.robots},
        time.perf_counter() - t0,
    )


def run_distributed_benchmark(
    world: Path,
    out: Path,
    *,
    faults: list[Fault],
    config: Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict:
    """The world once in process and once per fault mode distributed, then the recovery timings; JSON-ready
    results (also written to ``out/distributed.json`` and ``out/distributed.md``)."""
    from shgm_slam.config import load_config

    scenario = json.loads((world / "scenario.json").read_text())
    robots = {r["name"]: world / r["name"] for r in scenario["robots"]}
    cfg = load_config(config)
    runs = []
    say = progress or (lambda _msg: None)
    say("in-process run")
    runs.append(run_in_process(robots, out / "run", cfg))
    for fault in faults:
        say(f"distributed, fault: {fault.value}")
        try:
            runs.append(run_distributed(robots, out / f"distributed-{fault.value}", fault=fault, config=config))
        except ShgmError as exc:
            runs.append(RunOutcome(f"distributed, {fault.value}", {}, {}, float("nan"), error=str(exc)))
    recoveries = []
    reference = next(iter(robots))
    for folder, label in ((out / "distributed-server" / "at-kill", "server killed mid-run (at the kill)"),
                          (out / "distributed-none", "no fault (whole journal, at the end)")):  # fmt: skip
        if (folder / "journal.bin").is_file():
            say(f"recovery timing: {label}")
            recoveries.append(time_recovery(folder, cfg, reference, label))
    fps = _frame_rate(robots)
    result = {"world": str(world), "frame_rate_hz": fps, "runs": [vars(r) for r in runs],
              "recovery": [vars(r) for r in recoveries]}  # fmt: skip
    frames = {n: len(open_sequence(str(p))) for n, p in robots.items()}
    for r in result["runs"]:
        t = r["traffic"]
        if t:
            r["kb_per_s_per_robot"] = {n: b / 1e3 / (frames[n] / fps) for n, b in t["bytes_by_robot"].items()}
            r["kb_per_s_per_robot_at_10hz"] = {n: b / 1e3 / (frames[n] / 10.0) for n, b in t["bytes_by_robot"].items()}
            down = t.get("bytes_sent_by_robot", {})
            r["kb_per_s_down_per_robot_at_10hz"] = {n: b / 1e3 / (frames[n] / 10.0) for n, b in down.items()}
    write_report(out, "distributed", result, distributed_markdown, indent=2)
    return result


def _frame_rate(robots: dict[str, Path]) -> float:
    t = np.asarray(open_sequence(str(next(iter(robots.values())))).timestamps_s)
    return float(1.0 / np.median(np.diff(t))) if len(t) > 1 else float("nan")


def distributed_markdown(result: dict) -> str:
    """The README's tables: placement and fused ATE per run, traffic per distributed run, recovery timings."""
    runs = result["runs"]
    robots = list(runs[0]["placed"]) if runs else []
    head = "| run | " + " | ".join(f"{r} placed / ATE m" for r in robots) + " | wall s |"
    lines = [head, "|" + "---|" * (len(robots) + 2)]
    for r in runs:
        if r["error"]:
            lines.append(f"| {r['label']} | " + " | ".join("—" for _ in robots) + f" | failed: {r['error']} |")
            continue
        cells = [
            f"{'yes' if r['placed'].get(n) else 'no'} / {r['ate_fused_m'].get(n, float('nan')):.2f}" for n in robots
        ]
        lines.append(f"| {r['label']} | " + " | ".join(cells) + f" | {r['wall_s']:.0f} |")
    lines += ["", "| run | bytes / keyframe | keyframe messages | KB/s up per robot at 10 Hz | "
              "KB/s down per robot at 10 Hz | server → robots KB (corrections + status) |",
              "|---|---|---|---|---|---|"]  # fmt: skip
    for r in runs:
        t = r["traffic"]
        if not t:
            continue
        up = ", ".join(f"{n} {v:.1f}" for n, v in sorted(r["kb_per_s_per_robot_at_10hz"].items()))
        down = ", ".join(f"{n} {v:.2f}" for n, v in sorted(r.get("kb_per_s_down_per_robot_at_10hz", {}).items()))
        corr, status = (t["bytes_sent_by_kind"].get(k, 0) / 1e3 for k in ("correction", "status"))
        lines.append(f"| {r['label']} | {t['bytes_per_keyframe']:.0f} | {t['messages_by_kind'].get('keyframe', 0)} | "
                     f"{up} | {down} | {corr:.0f} + {status:.0f} |")  # fmt: skip
    rec = result.get("recovery", [])
    if rec:
        lines += ["", "| recovered folder | journal records | from snapshot | replayed | snapshot MB | "
                  "s with snapshots | s journal only | speed-up |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for r in rec:
            ratio = r["journal_only_s"] / r["snapshot_s"] if r["snapshot_s"] > 0 else float("nan")
            mb = r.get("snapshot_bytes", 0) / 1e6
            lines.append(f"| {r['label']} | {r['journal_records']} | {r['snapshot_records']} | {r['replayed']} | "
                         f"{mb:.2f} | {r['snapshot_s']:.1f} | {r['journal_only_s']:.1f} | {ratio:.1f}x |")  # fmt: skip
    return "\n".join(lines) + "\n"
