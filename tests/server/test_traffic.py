"""The server's traffic counts (``server.json``'s ``traffic``)."""

from __future__ import annotations

import json

from shgm_slam.server.traffic import TrafficStats


def test_counts_add_up_by_kind_and_robot_and_refusals_keep_fifty_reasons() -> None:
    t = TrafficStats()
    assert t.to_json_dict()["bytes_per_keyframe"] is None  # no keyframe yet: no mean, not a division by zero
    for size, robot in ((100, "car1"), (300, "car2"), (200, "car1")):
        t.add("keyframe", size, robot)
    t.add("hello", 10, "car1")
    t.sent("correction", 40, "car1")
    t.sent("status", 5)
    for i in range(60):
        t.refuse(f"bad message {i}")
    d = json.loads(json.dumps(t.to_json_dict()))  # plain JSON
    assert d["bytes_by_kind"] == {"keyframe": 600, "hello": 10} and d["messages_by_kind"] == {"keyframe": 3, "hello": 1}
    assert d["bytes_by_robot"] == {"car1": 310, "car2": 300} and d["bytes_per_keyframe"] == 200.0
    assert d["bytes_sent_by_kind"] == {"correction": 40, "status": 5} and d["bytes_sent_by_robot"] == {"car1": 40}
    assert d["refused"] == 60 and len(d["refusal_reasons"]) == 50 and d["refusal_reasons"][0] == "bad message 0"
