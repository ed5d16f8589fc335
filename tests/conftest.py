"""Shared fixtures. Real KITTI data is read from ../shared/data and tests that need it skip cleanly."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (real KITTI poses and frames); skips the test when it is absent."""
    if not (SHARED_DATA / "kitti").is_dir():
        pytest.skip("../shared/data/kitti is absent (real KITTI data is not part of the repository)")
    return SHARED_DATA


TINY_SCENARIO = {
    "scenario": "airsim-like",
    "seed": 0,
    "resolution": (320, 96),
    "fps": 4.0,
    "compact": True,
    "uav_speed_mps": 12.0,
}
"""Options of ``tiny_scenario``: compact airsim-like world, cars ~120 m, UAV ~150 m, ~45-60 frames each."""


@pytest.fixture(scope="session")
def tiny_scenario(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated airsim-like scenario (robots ``car1``, ``car2``, ``uav`` at 320x96, 4 Hz, with
    depth, labels and GT poses in one shared world frame), rendered once per session.

    Returns the output folder: ``<dir>/{car1,car2,uav}/`` sequences, ``world.json``, ``scenario.json``.
    """
    from shgm_slam.sim.simulate import simulate

    out = tmp_path_factory.mktemp("tiny_scenario")
    options = dict(TINY_SCENARIO)
    simulate(options.pop("scenario"), out, **options)
    return out


@pytest.fixture
def python_ctrl_c():
    """Ctrl-C raises KeyboardInterrupt through Python's own handler for the test, whatever an earlier test's
    libraries (a Rerun or Zenoh runtime registers native signal handlers) or pytest-xdist's workers (which ignore
    SIGINT) left installed; put back after."""
    import signal

    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)
