"""Test helpers that watch what the pipeline passes to a stage."""

from __future__ import annotations

from types import ModuleType

import pytest


def record_depth_percentiles(monkeypatch: pytest.MonkeyPatch, module: ModuleType) -> list:
    """Wrap ``module.extract_objects`` so every call's ``depth_percentiles`` argument is appended to the
    returned list (the call itself runs unchanged)."""
    seen: list = []
    original = module.extract_objects

    def spy(*args, **kwargs):
        seen.append(kwargs.get("depth_percentiles"))
        return original(*args, **kwargs)

    monkeypatch.setattr(module, "extract_objects", spy)
    return seen
