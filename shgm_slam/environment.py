"""What produced a result: this package, Python, the processor and the libraries whose arithmetic moves the
numbers.

The same code gives other trajectories on another processor or with other library versions (KISS-ICP's steps
move in the last digits, and the matches and closures follow: ``make demo`` gave 0.91 / 2.11 / 1.65 m on one
machine and 1.25 / 2.80 / 2.19 m on another, each deterministic). ``metrics.json`` and every benchmark's JSON
carry this record, so a number can be traced to what computed it.
"""

from __future__ import annotations

import functools
import importlib.metadata
import platform
from pathlib import Path

from shgm_slam import __version__

LIBRARIES = ("numpy", "scipy", "kiss-icp", "gtsam", "opencv-python-headless", "onnxruntime", "rerun-sdk")
"""Distributions whose versions are recorded (the ones whose arithmetic or behaviour moves results)."""


@functools.cache
def environment() -> dict:
    """``{"shgm_slam", "python", "machine", "processor", "libraries": {name: version or None}}`` of this process
    (computed once)."""
    versions: dict[str, str | None] = {}
    for name in LIBRARIES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "shgm_slam": __version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "processor": processor_name(),
        "libraries": versions,
    }


def processor_name(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The processor's model name (Linux: ``/proc/cpuinfo``'s first ``model name``; elsewhere
    ``platform.processor()``; '' when neither says)."""
    try:
        with open(cpuinfo, encoding="utf-8", errors="replace") as fh:
            for line in fh:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and value.strip():
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or ""


def environment_line(env: dict) -> str:
    """One markdown line naming what computed a report (``environment``'s dict), for its foot."""
    libs = ", ".join(f"{name} {version}" for name, version in env.get("libraries", {}).items() if version)
    where = env.get("processor") or env.get("machine") or "an unknown processor"
    return f"_Computed by shgm_slam {env.get('shgm_slam')} on {where}, Python {env.get('python')}; {libs}._"
