"""Rendered worlds in a shared cache (``sim/cache.py``): rendered once, by one process at a time, and never
seen half-written."""

from __future__ import annotations

import threading
import time

import pytest

from shgm_slam.errors import SimulationError
from shgm_slam.sim.cache import simulate_cached


@pytest.fixture()
def renders(monkeypatch):
    """A fake ``simulate`` that takes a while, writes scenario.json last and records every call."""
    calls = []

    def fake(scenario, out, *, overwrite=False, seed=0, fail=False):
        calls.append((scenario, out, seed))
        out.mkdir(parents=True, exist_ok=overwrite)
        (out / "car1").mkdir()
        time.sleep(0.2)
        if fail:
            raise SimulationError("renderer failed")
        (out / "scenario.json").write_text("{}")

    monkeypatch.setattr("shgm_slam.sim.cache.simulate", fake)
    return calls


def test_a_world_is_rendered_once_and_reused(tmp_path, renders):
    folder = tmp_path / "cache" / "airsim-like-s3"
    assert simulate_cached("airsim-like", folder, seed=3) == folder
    assert simulate_cached("airsim-like", folder, seed=3) == folder
    assert len(renders) == 1 and renders[0][1] != folder  # rendered beside it, then renamed into place
    assert (folder / "scenario.json").is_file() and (folder / "car1").is_dir()
    assert sorted(p.name for p in folder.parent.iterdir()) == ["airsim-like-s3", "airsim-like-s3.lock"]


def test_two_benchmarks_started_together_render_the_world_once(tmp_path, renders):
    folder = tmp_path / "airsim-like-s4"
    errors = []

    def one():
        try:
            simulate_cached("airsim-like", folder, seed=4)
        except Exception as e:
            errors.append(e)

    threads = [threading.Thread(target=one) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and len(renders) == 1 and (folder / "scenario.json").is_file()


def test_an_interrupted_render_is_replaced_and_a_failed_one_leaves_nothing(tmp_path, renders):
    folder = tmp_path / "synthia-like-s5"
    (folder / "car1" / "image_2").mkdir(parents=True)  # an earlier run killed mid-render: no scenario.json
    (folder / "car1" / "image_2" / "000007.png").write_bytes(b"")
    killed = tmp_path / "synthia-like-s5.partial-99999999"  # a render killed outright left its own folder
    (killed / "car1").mkdir(parents=True)
    other_world = tmp_path / "synthia-like-s55.partial-99999999"  # another world's: not this render's to remove
    other_world.mkdir()
    simulate_cached("synthia-like", folder, seed=5)
    assert (folder / "scenario.json").is_file() and not (folder / "car1" / "image_2").exists()
    assert not killed.exists() and other_world.is_dir()
    other_world.rmdir()

    other = tmp_path / "synthia-like-s6"
    with pytest.raises(SimulationError, match="renderer failed"):
        simulate_cached("synthia-like", other, seed=6, fail=True)
    assert not other.exists() and not list(tmp_path.glob("*.partial-*"))


def test_a_file_where_the_world_goes_is_refused(tmp_path, renders):
    (tmp_path / "w").write_text("x")
    with pytest.raises(SimulationError, match="it is a file"):
        simulate_cached("airsim-like", tmp_path / "w")
    with pytest.raises(SimulationError, match="cannot create the cache folder"):
        simulate_cached("airsim-like", tmp_path / "w" / "airsim-like-s1")  # the cache itself is a file
    assert renders == []
