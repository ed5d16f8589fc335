"""Wire codec: exact round trips of every message, compact keyframes, and refusal of anything malformed."""

from __future__ import annotations

import time
from dataclasses import replace

import msgpack
import numpy as np
import pytest

from shgm_slam.errors import ProtocolError, ShgmError
from shgm_slam.geometry.se3 import make_pose, rot_y, so3_exp
from shgm_slam.graph.extraction import ObjectObservations
from shgm_slam.graph.semantic_graph import GraphUpdate, NodeState, SemanticGraph
from shgm_slam.messages import (
    AgentCorrection,
    CorrectionMessage,
    DoneMessage,
    HelloMessage,
    KeyframeMessage,
    RobotState,
    RobotStatus,
    RobotTrajectory,
    StatusMessage,
)
from shgm_slam.wire import PROTOCOL_VERSION, MessageKind, WireError, decode, encode


def observations(labels, points_cam, pixels=None) -> ObjectObservations:
    p = np.asarray(points_cam, dtype=np.float64).reshape(-1, 3)
    n = p.shape[0]
    px = np.full(n, 100) if pixels is None else np.asarray(pixels)
    return ObjectObservations(np.asarray(labels, np.int64), p, p.copy(), px, np.ones((n, 3)))


def pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_pose(so3_exp(rng.normal(0, 1, 3)), rng.normal(0, 50, 3))


def graph_updates() -> list[GraphUpdate]:
    """Three keyframes of a real graph: new nodes, merges, and an empty update."""
    g = SemanticGraph(merge_radius_m=3.0, connectivity_m=10.0)
    T1 = make_pose(rot_y(0.2), np.array([1.0, 0.0, 2.0]))
    u0 = g.add_keyframe(0, np.eye(4), observations([2, 5, 13], [[0, 0, 10], [3, 1, 12], [-4, 0, 8]], [50, 7, 900]))
    u1 = g.add_keyframe(1, T1, observations([2, 18], [[-1.5, 0.2, 8.4], [10, -1, 20]], [60, 3]))
    u2 = g.add_keyframe(2, T1 @ T1, observations([], np.zeros((0, 3))))
    assert u0.new_nodes and u1.updated_nodes and not (u2.new_nodes or u2.updated_nodes)
    return [u0, u1, u2]


def random_update(n: int, seed: int = 0) -> GraphUpdate:
    rng = np.random.default_rng(seed)
    nodes = tuple(
        NodeState(int(rng.integers(0, 10**6)), int(rng.integers(0, 19)), int(rng.integers(0, 8)),
                  tuple(rng.uniform(-50, 50, 3).tolist()), float(rng.integers(10, 10**5)), int(rng.integers(1, 40)))
        for _ in range(n)
    )  # fmt: skip
    return GraphUpdate(7, pose(seed), nodes[: n // 2], nodes[n // 2 :])


def keyframe(update: GraphUpdate, up: bool = True, robot: str = "car_1#2") -> KeyframeMessage:
    return KeyframeMessage(robot, update.kf_id, 3 * update.kf_id + 1, 12.5 + update.kf_id, update.T_world_kf,
                           update, np.array([0.0, -1.0, 0.0]) if up else None, "a1b2c3d4e5f6a7b8")  # fmt: skip


def all_messages() -> list:
    n = 6
    seg = np.array([0, 0, -1, 1, 1, 1])
    T = np.stack([pose(i) for i in range(n)])
    T[seg < 0] = np.nan
    traj = RobotTrajectory(np.arange(n) * 0.1, seg, T)
    updates = graph_updates()
    return [
        HelloMessage("car1", "0123456789abcdef", 4541),
        HelloMessage("car1", "0123456789abcdef", 4541, resync=True),
        HelloMessage("car1", "0123456789abcdef", 4541, start_s=1.3e9, progress_s=12.5),
        HelloMessage("car1", "0123456789abcdef", 4541, settings_digest="93453205442ead31"),
        *[keyframe(u) for u in updates],
        keyframe(updates[0], up=False, robot="car1"),
        KeyframeMessage("r", 1, 1, 0.0, pose(3), updates[1], None, ""),  # graph pose differs from the keyframe pose
        DoneMessage("car1", "s1", {"car1": 10, "car1#1": 0}, traj),
        DoneMessage("car1", "s1", {}, None),
        DoneMessage("car1", "s1", {"car1": 2}, None,
                    {"extraction": {"max_depth_m": 61.5}, "odometry": {"cloud_stride": 2, "shuffle_points": True}}),
        CorrectionMessage("car1", "", {"car1": 3, "car1#1": 2}),  # acknowledgement alone
        CorrectionMessage(
            "car1", "s1", {"car1": 3}, 1, True,
            {"car1": AgentCorrection(pose(7), 3, np.arange(3), np.stack([pose(i) for i in range(3)]))},
        ),
        CorrectionMessage(
            "car1", "s1", {"car1": 5, "car1#1": 2}, 2, False,
            {"car1": AgentCorrection(pose(8), 5, np.array([1, 3, 4]), np.stack([pose(i) for i in range(3)]), pose(9)),
             "car1#1": AgentCorrection(None)},
        ),
        StatusMessage(
            "srv",
            "car1",
            {
                "car1": RobotStatus(RobotState.ACTIVE, 12, ("car1",), ("car1", "car1#1")),
                "car3": RobotStatus(RobotState.ACTIVE, 7, ("car3", "car3#1"), ("car3", "car3#1"), ("car3#1",)),
                "car2": RobotStatus(RobotState.DONE, 4, (), ("car2",), (), ("car2",)),
                "b-3": RobotStatus(RobotState.STALE, 5, (), ("b-3",)),
            },
            True,
            {"car9": "s9: name in use by another running robot"},
        ),
        StatusMessage("", "", {}),
    ]


def assert_same(a, b) -> None:
    """Field-by-field equality of messages (arrays exactly, node positions/sizes at float32 precision)."""
    assert type(a) is type(b)
    if isinstance(a, GraphUpdate):
        assert a.kf_id == b.kf_id
        np.testing.assert_array_equal(a.T_world_kf, b.T_world_kf)
        for xs, ys in ((a.new_nodes, b.new_nodes), (a.updated_nodes, b.updated_nodes)):
            assert len(xs) == len(ys)
            for x, y in zip(xs, ys, strict=True):
                assert (x.node_id, x.label_id, x.anchor_kf, x.num_observations) == (
                    y.node_id, y.label_id, y.anchor_kf, y.num_observations)  # fmt: skip
                np.testing.assert_array_equal(np.float32(x.position_kf), y.position_kf)
                assert np.float32(x.size) == y.size
        return
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, GraphUpdate | RobotTrajectory | AgentCorrection):
            assert_same(x, y)
        elif isinstance(x, dict) and any(isinstance(v, AgentCorrection) for v in x.values()):
            assert x.keys() == y.keys()
            for k in x:
                assert_same(x[k], y[k])
        elif isinstance(x, np.ndarray) or (isinstance(x, dict) and any(isinstance(v, np.ndarray) for v in x.values())):
            xs, ys = (x, y) if isinstance(x, dict) else ({0: x}, {0: y})
            assert xs.keys() == ys.keys()
            for k in xs:
                assert ys[k].dtype == np.asarray(xs[k]).dtype
                np.testing.assert_array_equal(xs[k], ys[k])  # NaN == NaN here
        else:
            assert x == y, name


@pytest.mark.parametrize("msg", all_messages(), ids=lambda m: type(m).__name__)
def test_every_message_round_trips(msg):
    payload = encode(msg)
    assert isinstance(payload, bytes)
    out = decode(payload)
    assert_same(msg, out)
    assert encode(out) == payload  # decoded values are fixed points: both runs see identical values


def test_a_status_without_provisional_or_waiting_agents_or_a_share_is_still_read():
    """Older servers' statuses have four items per robot (no provisional agents), five (no waiting agents) or
    six (no segments allowed): read as none (0: not said)."""
    import msgpack

    payload = encode(StatusMessage("srv", "car1", {"car1": RobotStatus(RobotState.ACTIVE, 3, ("car1",), ("car1",),
                                                                       ("car1",), ("car1#1",), 17)}))  # fmt: skip
    fields = msgpack.unpackb(payload, raw=False)
    assert len(fields["b"]["car1"]) == 7
    assert decode(payload).robots["car1"].waiting_agents == ("car1#1",)
    assert decode(payload).robots["car1"].segments_allowed == 17
    full = list(fields["b"]["car1"])
    fields["b"]["car1"] = full[:6]
    status = decode(msgpack.packb(fields, use_bin_type=True)).robots["car1"]
    assert status.waiting_agents == ("car1#1",) and status.segments_allowed == 0
    fields["b"]["car1"] = full[:5]
    status = decode(msgpack.packb(fields, use_bin_type=True)).robots["car1"]
    assert status.provisional_agents == ("car1",) and status.waiting_agents == ()
    fields["b"]["car1"] = full[:4]
    status = decode(msgpack.packb(fields, use_bin_type=True)).robots["car1"]
    assert status.placed_agents == ("car1",) and status.provisional_agents == () and status.waiting_agents == ()
    fields["b"]["car1"] = [*full, ["car1"]]  # eight items: refused
    with pytest.raises(WireError, match="segments allowed"):
        decode(msgpack.packb(fields, use_bin_type=True))
    fields["b"]["car1"] = [*full[:6], "many"]  # a share that is no integer: refused
    with pytest.raises(WireError, match="segments allowed of 'car1' must be an integer"):
        decode(msgpack.packb(fields, use_bin_type=True))


def test_keyframe_bytes_are_compact():
    sizes = {n: len(encode(keyframe(random_update(n, seed=n)))) for n in (0, 10, 30, 100)}
    K = 100
    poses = np.stack([pose(i) for i in range(K)])
    corr = CorrectionMessage("car1", "0123456789abcdef", {"car1": K}, 1, True,
                             {"car1": AgentCorrection(pose(0), K, np.arange(K), poses)})  # fmt: skip
    delta = CorrectionMessage("car1", "0123456789abcdef", {"car1": K}, 2, False,
                              {"car1": AgentCorrection(pose(0), K, np.arange(K - 3, K), poses[-3:])})  # fmt: skip
    ack = CorrectionMessage("car1", "0123456789abcdef", {"car1": K})
    print(f"keyframe bytes by node count: {sizes}; correction with {K} keyframes: {len(encode(corr))} bytes, "
          f"with 3: {len(encode(delta))}, acknowledgement: {len(encode(ack))}")  # fmt: skip
    assert len(encode(delta)) < 500 and len(encode(ack)) < 80
    assert K * 100 <= len(encode(corr)) <= K * 100 + 300  # 96 B pose + 4 B index per keyframe
    assert sizes[30] <= 5 * 1024
    assert 100 * 31 <= sizes[100] - sizes[0] <= 100 * 31 + 12  # 31 bytes a node (+ bin header growth)


def test_error_is_one_shgm_exception():
    assert issubclass(WireError, ProtocolError) and issubclass(WireError, ShgmError)


def _envelope(msg) -> dict:
    return msgpack.unpackb(encode(msg), raw=False)


def _pack(d: dict) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def _refused_with(msg, path: tuple, value, what: str) -> None:
    """``msg``'s valid payload with the field at ``path`` (keys into the envelope) set to ``value``, or to what
    ``value`` makes of the field's bytes when callable: decoding it raises a WireError matching ``what``."""
    d = _envelope(msg)
    parent = d
    for k in path[:-1]:
        parent = parent[k]
    parent[path[-1]] = value(parent[path[-1]]) if callable(value) else value
    with pytest.raises(WireError, match=what):
        decode(_pack(d))


def test_unknown_version_names_both_versions():
    d = _envelope(HelloMessage("car1", "s", 1))
    d["v"] = 99
    with pytest.raises(WireError, match=rf"version 99.*speaks {PROTOCOL_VERSION}"):
        decode(_pack(d))
    del d["v"]
    with pytest.raises(WireError, match="version None"):
        decode(_pack(d))


@pytest.mark.parametrize("kind", [0, 6, -1, "hello", None, 2.0, True])
def test_unknown_kind(kind):
    d = _envelope(HelloMessage("car1", "s", 1))
    d["k"] = kind
    with pytest.raises(WireError, match="kind"):
        decode(_pack(d))


def test_kind_and_fields_must_agree():
    d = _envelope(HelloMessage("car1", "s", 1))
    d["k"] = int(MessageKind.DONE)
    with pytest.raises(WireError, match="done message has fields"):
        decode(_pack(d))
    d = _envelope(HelloMessage("car1", "s", 1))
    d["zz"] = 1
    with pytest.raises(WireError, match="unknown"):
        decode(_pack(d))
    d = _envelope(HelloMessage("car1", "s", 1))
    d["n"] = True
    with pytest.raises(WireError, match="num_frames must be an integer"):
        decode(_pack(d))


def test_nan_and_non_rigid_poses_are_refused():
    msg = keyframe(random_update(4))
    bad = msg.T_odom_kf.copy()
    bad[0, 3] = np.nan
    with pytest.raises(WireError, match="NaN"):
        encode(KeyframeMessage(msg.robot, 0, 0, 0.0, bad, msg.graph_update))
    d = _envelope(msg)
    P = np.frombuffer(d["T"], "<f8").copy()
    P[5] = np.inf
    d["T"] = P.tobytes()
    with pytest.raises(WireError, match="NaN or infinite"):
        decode(_pack(d))
    P = np.frombuffer(_envelope(msg)["T"], "<f8").reshape(3, 4).copy()
    P[:, :3] *= 1.001  # scaled rotation
    d["T"] = P.tobytes()
    with pytest.raises(WireError, match="not orthonormal"):
        decode(_pack(d))
    P[:, :3] = np.diag([1.0, 1.0, -1.0])  # reflection
    d["T"] = P.tobytes()
    with pytest.raises(WireError, match="det"):
        decode(_pack(d))
    with pytest.raises(WireError, match="timestamp_s must be finite"):
        encode(KeyframeMessage(msg.robot, 0, 0, float("nan"), msg.T_odom_kf, msg.graph_update))


def test_wrong_array_lengths_are_refused():
    d = _envelope(keyframe(random_update(10)))
    d["gn"]["p"] = d["gn"]["p"][:-4]
    with pytest.raises(WireError, match=r"new nodes\.p has 56 bytes, expected 5 x 12"):
        decode(_pack(d))
    d = _envelope(keyframe(random_update(10)))
    d["gu"]["i"] = d["gu"]["i"][:-3]
    with pytest.raises(WireError, match="multiple of 8"):
        decode(_pack(d))
    d = _envelope(keyframe(random_update(10)))
    d["T"] = d["T"] + d["T"]
    with pytest.raises(WireError, match="expected 1 x 96"):
        decode(_pack(d))
    d = _envelope(next(m for m in all_messages() if isinstance(m, DoneMessage)))  # with a trajectory
    d["j"]["g"] = d["j"]["g"][:-4]
    with pytest.raises(WireError, match=r"trajectory\.g"):
        decode(_pack(d))


def test_node_values_out_of_range_are_refused():
    u = random_update(2)
    for state, what in [
        (NodeState(1, 300, 0, (0.0, 0.0, 1.0), 1.0, 1), "label ids"),
        (NodeState(1, 2, -1, (0.0, 0.0, 1.0), 1.0, 1), "anchor"),
        (NodeState(1, 2, 0, (np.nan, 0.0, 1.0), 1.0, 1), "finite"),
        (NodeState(1, 2, 0, (1e39, 0.0, 1.0), 1.0, 1), "finite"),
        (NodeState(2**63, 2, 0, (0.0, 0.0, 1.0), 1.0, 1), "int64"),
    ]:
        with pytest.raises(WireError, match=what):
            encode(keyframe(GraphUpdate(0, u.T_world_kf, (state,), ())))
    big = NodeState(1, 2, 0, (0.0, 0.0, 1.0), 1.0, 10**6)  # observation counts saturate
    out = decode(encode(keyframe(GraphUpdate(0, u.T_world_kf, (big,), ()))))
    assert out.graph_update.new_nodes[0].num_observations == 65535


@pytest.mark.parametrize("name", ["", "1car", "car 1", "car#0", "car#", "car#01", "a" * 33, "car1#1#2", "ca/r", "ü"])
def test_bad_agent_names_are_refused(name):
    with pytest.raises(WireError, match="invalid"):
        encode(keyframe(random_update(2), robot=name))
    d = _envelope(keyframe(random_update(2)))
    d["r"] = name
    with pytest.raises(WireError, match="invalid"):
        decode(_pack(d))


def test_names_sessions_and_indices_are_checked():
    with pytest.raises(WireError, match="hello robot"):
        encode(HelloMessage("car1#1", "s", 1))  # a robot, not a segment
    with pytest.raises(WireError, match="session"):
        encode(HelloMessage("car1", "x" * 65, 1))
    with pytest.raises(WireError, match="session"):
        encode(HelloMessage("car1", "a b", 1))
    with pytest.raises(WireError, match="progress_s must be >= 0"):
        encode(HelloMessage("car1", "s", 1, progress_s=-1.0))
    d = _envelope(HelloMessage("car1", "s", 1))
    d["b"] = float("nan")
    with pytest.raises(WireError, match="start_s must be finite"):
        decode(_pack(d))
    with pytest.raises(WireError, match="not an agent of robot"):
        encode(CorrectionMessage("car1", "", {"car2": 1}))
    d = _envelope(keyframe(random_update(2)))
    d["i"] = -1
    with pytest.raises(WireError, match=r"kf_index = -1 is out of range"):
        decode(_pack(d))
    d = _envelope(all_messages()[-2])
    d["y"] = {"car9": "line\nbreak"}
    with pytest.raises(WireError, match="printable"):
        decode(_pack(d))
    d = _envelope(all_messages()[-2])
    d["b"]["car1"][0] = 7
    with pytest.raises(WireError, match="state"):
        decode(_pack(d))


@pytest.mark.parametrize(
    ("settings", "culprit"),
    [
        ({"extraction": {"max_depth_m": float("nan")}}, r"done settings\[extraction\]\[max_depth_m\] must be finite"),
        ({"extraction": {"max_depth_m": "far"}}, "must be a number"),
        ({"extraction": [1, 2]}, r"done settings\[extraction\] must be a map"),
        ({"Extraction": {}}, "done settings stage 'Extraction' is invalid"),
        ({"odometry": {"bad name": 1}}, "field 'bad name' is invalid"),
        ([1], "done settings must be a map"),
    ],
)
def test_settings_and_digests_are_checked(settings, culprit):
    d = _envelope(DoneMessage("car1", "s", {}))
    d["e"] = settings
    with pytest.raises(WireError, match=culprit):
        decode(_pack(d))
    with pytest.raises(WireError, match="settings_digest"):
        encode(HelloMessage("car1", "s", 1, settings_digest="ABC"))  # lowercase hex only
    d = _envelope(HelloMessage("car1", "s", 1))
    d["d"] = "0" * 65
    with pytest.raises(WireError, match="settings_digest"):
        decode(_pack(d))


def test_oversize_payloads_are_refused():
    with pytest.raises(WireError, match="limit"):
        decode(b"\x00" * (16 * 1024 * 1024 + 1))
    many = {f"car1#{i + 1}": 1 for i in range(5000)}
    with pytest.raises(WireError, match="at most 4096"):
        encode(CorrectionMessage("car1", "", many))
    with pytest.raises(WireError, match="not one valid msgpack"):
        decode(_pack({"v": PROTOCOL_VERSION, "k": 4, "r": "car1", "s": "", "c": many, "q": 0, "F": False, "A": {}}))
    with pytest.raises(WireError, match="not one valid msgpack"):
        decode(_pack({"v": PROTOCOL_VERSION, "k": 1, "r": "car1", "s": "x" * 10_000, "n": 1, "y": False}))
    with pytest.raises(WireError, match="not one valid msgpack"):
        decode(b"\x91" * 100_000)  # nested arrays


def test_garbage_and_non_maps_are_refused():
    for payload in [b"", b"\xc1", _pack([1, 2]), _pack(5), encode(HelloMessage("a", "s", 1)) + b"\x00"]:
        with pytest.raises(WireError):
            decode(payload)
    with pytest.raises(WireError, match="payload must be bytes"):
        decode("text")  # type: ignore[arg-type]
    with pytest.raises(WireError, match="cannot encode"):
        encode(object())  # type: ignore[arg-type]


def test_fuzz_decodes_or_refuses():
    """Random bytes, every truncation and single-byte flips of valid payloads: a message or WireError only."""
    rng = np.random.default_rng(1234)
    valid = [encode(m) for m in all_messages()] + [encode(keyframe(random_update(30)))]
    cases: list[bytes] = [rng.bytes(int(rng.integers(0, 300))) for _ in range(1000)]
    cases += [bytes([0x80 | int(rng.integers(0, 16))]) + rng.bytes(int(rng.integers(0, 200))) for _ in range(500)]
    for p in valid:
        cases += [p[:i] for i in range(len(p))] if len(p) < 2000 else [p[:i] for i in rng.integers(0, len(p), 300)]
        for _ in range(200):
            b = bytearray(p)
            b[int(rng.integers(0, len(b)))] = int(rng.integers(0, 256))
            cases.append(bytes(b))
    assert len(cases) > 4000
    t0 = time.perf_counter()
    decoded = 0
    for p in cases:
        try:
            msg = decode(p)
        except WireError as exc:
            assert "\n" not in str(exc)
            continue
        encode(msg)  # what decode accepts, encode accepts: the two check the same rules
        decoded += 1
    print(f"fuzz: {len(cases)} cases, {decoded} decoded, {time.perf_counter() - t0:.2f} s")
    assert decoded > 0


def test_wrong_field_types_decode_or_refuse():
    """Every field (and node column) of every message replaced by values of other types: WireError, no crash."""
    values = [None, True, -1, 2**40, 1.5, float("nan"), "x", b"\x00" * 8, [], [1, "a"], {}, {"a": 1}]
    refused = 0
    for msg in [*all_messages(), keyframe(random_update(6))]:
        env = _envelope(msg)
        paths = [(k,) for k in env] + [
            (k, c) for k in ("gn", "gu", "j") if isinstance(env.get(k), dict) for c in env[k]
        ]
        for path in paths:
            for v in values:
                d = _envelope(msg)
                parent = d if len(path) == 1 else d[path[0]]
                parent[path[-1]] = v
                try:
                    encode(decode(_pack(d)))
                except WireError:
                    refused += 1
    assert refused > 500


def test_correction_indices_and_unplaced_agents_are_checked():
    T = np.stack([pose(i) for i in range(3)])
    for c, what in [
        (AgentCorrection(pose(0), 3, np.array([0, 2, 1]), T), "increase"),
        (AgentCorrection(pose(0), 2, np.array([0, 1, 2]), T), "increase"),
        (AgentCorrection(pose(0), 3, np.array([0, 1]), T), "2 keyframe indices but 3 poses"),
        (AgentCorrection(None, 3, np.arange(3), T), "not placed"),
        (AgentCorrection(None, T_move=pose(1)), "not placed"),
    ]:
        with pytest.raises(WireError, match=what):
            encode(CorrectionMessage("car1", "", {}, 1, False, {"car1": c}))
    good = CorrectionMessage("car1", "", {}, 1, False, {"car1": AgentCorrection(pose(0), 3, np.arange(3), T)})
    _refused_with(good, ("A", "car1", "i"), np.array([0, 5, 6], "<i4").tobytes(), r"increase within 0\.\.2")
    _refused_with(good, ("A", "car1", "o"), None, "not placed")
    _refused_with(good, ("F",), 1, "full must be true or false")


def _with_update(msg: KeyframeMessage, **changes) -> KeyframeMessage:
    return replace(msg, graph_update=replace(msg.graph_update, **changes))


def test_keyframes_the_map_server_cannot_apply_are_refused_both_ways():
    """Decodable before, and each one stopped ``shgm-slam server`` with a stack trace (a GraphError or BackendError
    from deep in the map) or wrote garbage: a label no class has, a graph update of another keyframe, a node anchored
    to a keyframe after its own, a zero ground normal, a translation of 1e300 m."""
    msg = keyframe(graph_updates()[1])  # keyframe 1: a new node anchored to it, merged ones anchored to keyframe 0
    node = msg.graph_update.new_nodes[0]
    far = msg.T_odom_kf.copy()
    far[0, 3] = 1e300
    for bad, what in [
        (_with_update(msg, new_nodes=(replace(node, label_id=19),)), "label ids must be Cityscapes train ids 0..18"),
        (_with_update(msg, new_nodes=(replace(node, label_id=255),)), "label ids must be Cityscapes train ids 0..18"),
        (_with_update(msg, kf_id=0), "keyframe 1 carries the graph update of keyframe 0"),
        (_with_update(msg, new_nodes=(replace(node, anchor_kf=7),)), "anchored to keyframe 7, after it"),
        (replace(msg, up_odom=np.zeros(3)), "unit vector"),
        (replace(msg, up_odom=np.array([0.0, -2.0, 0.0])), "unit vector"),
        (replace(msg, T_odom_kf=far, graph_update=replace(msg.graph_update, T_world_kf=far)), "beyond 1e\\+08 m"),
        (_with_update(msg, new_nodes=(replace(node, position_kf=(1e30, 0.0, 0.0)),)), "within 1e\\+08 m"),
    ]:
        with pytest.raises(WireError, match=what):
            encode(bad)
    # the same values written straight into a valid payload's bytes: decode refuses them

    def edited(dtype: str, i: int, v: float):
        def edit(raw: bytes) -> bytes:
            a = np.frombuffer(raw, dtype).copy()
            a[i] = v
            return a.tobytes()
        return edit

    _refused_with(msg, ("gn", "l"), lambda raw: bytes([255]) * len(raw), "label ids")
    _refused_with(msg, ("gk",), 0, "graph update of keyframe 0")
    _refused_with(msg, ("gn", "a"), lambda raw: np.full(len(raw) // 4, 9, "<i4").tobytes(), "anchored to keyframe 9")
    _refused_with(msg, ("u",), np.zeros(3, "<f8").tobytes(), "unit vector")
    _refused_with(msg, ("T",), edited("<f8", 3, -1e300), "translation is beyond")
    _refused_with(msg, ("gn", "p"), edited("<f4", 0, 3e38), "node positions must be within")


def test_a_keyframe_of_more_nodes_than_an_image_can_hold_is_refused():
    """Half a million node states fit in 16 MB; the map server fed 20,000 in one place ran out of memory."""
    from shgm_slam.wire import MAX_NODES

    nodes = tuple(NodeState(i, 13, 0, (float(i % 50), 0.0, 5.0), 10.0, 1) for i in range(MAX_NODES + 1))
    with pytest.raises(WireError, match=f"at most {MAX_NODES} per keyframe"):
        encode(keyframe(GraphUpdate(0, np.eye(4), nodes, ())))
    d = _envelope(keyframe(GraphUpdate(0, np.eye(4), nodes[:MAX_NODES], ())))
    for k, width in [("i", 8), ("l", 1), ("a", 4), ("p", 12), ("z", 4), ("o", 2)]:
        d["gn"][k] += d["gn"][k][:width]  # one more node in every column
    with pytest.raises(WireError, match=f"{MAX_NODES + 1} node states"):
        decode(_pack(d))
