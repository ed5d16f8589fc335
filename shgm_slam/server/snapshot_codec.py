"""The body of a map-server snapshot: ``ServerSnapshot`` to msgpack bytes and back (never pickle).

Arrays are ``[dtype code, shape, raw little-endian bytes]`` with the dtype from a short list
(``f8``, ``i8``, ``b1``) and the byte count checked against the shape; names, counts and flags are
plain msgpack values. Decoding trusts nothing structurally: a field of the wrong type or shape, a
missing key or bytes that are not msgpack raise ``SnapshotError`` (one line). Whether the content is
consistent (keyframes that exist, closures between known robots, ...) is checked by
``MapServer.from_state`` and the graphs' and pose graph's own ``from_state`` / ``restore_state``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from shgm_slam.backend.consistency import PairVote
from shgm_slam.backend.records import ClosureRecord, ClosureStatus, Factorization
from shgm_slam.backend.state import PoseGraphState
from shgm_slam.errors import DataError, ShgmError
from shgm_slam.graph.semantic_graph import GraphState
from shgm_slam.messages import DoneMessage, RobotState
from shgm_slam.server.records import MatchEvidence, MatchRecord
from shgm_slam.server.sessions import RobotSession
from shgm_slam.server.state import MapServerState
from shgm_slam.wire import decode, encode

_DTYPES = {"f8": np.dtype("<f8"), "i8": np.dtype("<i8"), "b1": np.dtype("|b1")}
_GRAPH_FIELDS = (
    ("node_ids", "i8"), ("label_ids", "i8"), ("anchor_slots", "i8"), ("positions_kf", "f8"),
    ("positions_world", "f8"), ("sizes", "f8"), ("num_observations", "i8"), ("kf_ids", "i8"),
    ("T_world_kf", "f8"), ("obs_rows", "i8"), ("obs_slots", "i8"), ("edges", "i8"),
)  # fmt: skip
_CLOSURE_KEYS = ("keyframe_a", "keyframe_b", "inliers", "accepted", "reason")
_OPTIONAL_CLOSURE_KEYS = ("stretches",)  # absent in snapshots written before it existed


class SnapshotError(DataError):
    """A snapshot file is cut short, corrupt, of another version or malformed."""


@dataclass(frozen=True, eq=False)
class ServerSnapshot:
    """The map server's state after its first ``journal_records`` journal records.

    Attributes:
        journal_records: journal records the state includes; journal_chain: ``Journal.chain`` after them.
        config_digest: digest of the configuration the state was made with (``snapshot.config_digest``).
        reference: the robot whose frame is the shared frame (None before the first robot).
        sessions: each robot's session, keyframe times and frames, and its ``DoneMessage`` if any.
        map: the map server's state (None before the first robot).
    """

    journal_records: int
    journal_chain: int
    config_digest: str
    reference: str | None
    sessions: tuple[RobotSession, ...]
    map: MapServerState | None


# --- encode ---------------------------------------------------------------------------------------------


def _arr(a: Any, code: str) -> list:
    a = np.ascontiguousarray(a, dtype=_DTYPES[code])
    return [code, list(a.shape), a.tobytes()]


def _graph(g: GraphState) -> dict:
    return {"mr": g.merge_radius_m, "cm": g.connectivity_m, "next": g.next_node_id,
            **{name: _arr(getattr(g, name), code) for name, code in _GRAPH_FIELDS}}  # fmt: skip


def _match(m: MatchRecord) -> dict:
    return {
        "step": m.step, "a": m.robot_a, "b": m.robot_b, "q": m.query, "ok": m.success, "acc": m.accepted,
        "why": m.reason, "ka": m.kf_a, "kb": m.kf_b, "T": None if m.T_a_b is None else _arr(m.T_a_b, "f8"),
        "inl": _arr(np.asarray(m.inliers).reshape(-1, 2), "i8"), "cand": m.candidates, "na": m.nodes_a,
        "nb": m.nodes_b, "ms": {k: float(v) for k, v in m.timings_ms.items()},
        "pa": _arr(m.inlier_positions_a, "f8"), "pb": _arr(m.inlier_positions_b, "f8"),
        "cl": [_closure_dict(c) for c in m.closures],
        "dup": m.duplicate,
        "ev": None if m.evidence is None else _evidence(m.evidence),
    }  # fmt: skip


def _evidence(e: MatchEvidence) -> dict:
    return {"T": _arr(e.T_a_b_hypothesis, "f8"), "kb": e.keyframe_b, "llr": e.llr, "thr": e.llr_threshold,
            "sup": e.support, "ch": e.expected_chance, "oa": e.overlap_a, "ob": e.overlap_b,
            "rl": e.rival_llr, "cs": e.centroid_sigma_m}  # fmt: skip


def _closure(c: ClosureRecord) -> dict:
    return {"id": c.closure_id, "a": c.robot_a, "ka": c.kf_a, "b": c.robot_b, "kb": c.kf_b, "T": _arr(c.T_a_b, "f8"),
            "n": c.num_inliers, "st": c.status.value, "why": c.reason, "in": c.in_graph, "mid": c.match_id,
            "q": c.querier, "dec": c.decisive}  # fmt: skip


def _pose_graph(p: PoseGraphState) -> dict:
    return {
        "robots": list(p.robots),
        "anchors": {n: [cid, _arr(T, "f8")] for n, (cid, T) in p.anchors.items()},
        "est": {n: _arr(T, "f8") for n, T in p.T_shared_kf.items()},
        "closures": [_closure(c) for c in p.closures],
        "info": _arr(p.information, "f8"),
        "pairs": [[a, b, {"ids": _arr(v.ids, "i8"), "A": _arr(v.adjacency, "b1"), "w": _arr(v.weights, "f8"),
                          "ch": _arr(v.chosen, "b1"), "exact": v.exact, "n": v.searches}]
                  for (a, b), v in p.pairs.items()],
        "rebuilds": p.rebuilds, "recoveries": p.recoveries, "fact": p.factorization.value,
        "up": {n: _arr(u, "f8") for n, u in p.up_odom.items()},
    }  # fmt: skip


def _map(m: MapServerState) -> dict:
    return {
        "agents": list(m.agents), "graphs": {a: _graph(g) for a, g in m.graphs.items()},
        "T": {a: _arr(T, "f8") for a, T in m.T_odom_kf.items()},
        "up": {a: None if u is None else _arr(u, "f8") for a, u in m.up.items()},
        "since": dict(m.since_match), "matches": [_match(r) for r in m.matches],
        "closures": [list(c) for c in m.closures], "step": m.step, "nm": m.num_matches,
        "ms": {k: _arr(v, "f8") for k, v in m.timings_ms.items()}, "pg": _pose_graph(m.pose_graph),
        **_support(m.support),
        "offset": [float(v) for v in m.surface_offset],
    }  # fmt: skip


def _support(support: dict[int, dict[str, frozenset[int]]]) -> dict:
    """The objects each closure rests on, every distinct set once: all closures of one match rest on the
    same objects, so "support" holds [closure id, index into "support_sets"]."""
    sets: list[dict] = []
    index: dict[tuple, int] = {}
    rows = []
    for cid, sup in sorted(support.items()):
        key = tuple(sorted((a, tuple(sorted(ids))) for a, ids in sup.items()))
        if key not in index:
            index[key] = len(sets)
            sets.append({a: list(ids) for a, ids in key})  # msgpack packs small ids in 1-3 bytes
        rows.append([cid, index[key]])
    return {"support_sets": sets, "support": rows}


def _session(s: RobotSession) -> dict:
    return {"name": s.name, "session": s.session, "state": s.state.value,
            "done": None if s.done is None else encode(s.done),
            "t": {a: _arr(v, "f8") for a, v in s.kf_timestamps.items()},
            "f": {a: _arr(v, "i8") for a, v in s.kf_frames.items()}}  # fmt: skip


def encode_snapshot(snap: ServerSnapshot) -> bytes:
    """The snapshot body as msgpack bytes."""
    return msgpack.packb({
        "records": snap.journal_records, "chain": snap.journal_chain, "config": snap.config_digest,
        "reference": snap.reference, "sessions": [_session(s) for s in snap.sessions],
        "map": None if snap.map is None else _map(snap.map),
    }, use_bin_type=True)  # fmt: skip


# --- decode ---------------------------------------------------------------------------------------------


def _typed(v: Any, types: type | tuple[type, ...], what: str) -> Any:
    types = types if isinstance(types, tuple) else (types,)
    if not isinstance(v, types) or (type(v) is bool and bool not in types):  # msgpack bools are ints to Python
        raise SnapshotError(f"snapshot field {what} has the wrong type ({type(v).__name__})")
    return v


def _unarr(v: Any, code: str, what: str) -> np.ndarray:
    if not (isinstance(v, list) and len(v) == 3 and v[0] == code and isinstance(v[1], list)
            and isinstance(v[2], bytes) and len(v[1]) <= 4):  # fmt: skip
        raise SnapshotError(f"snapshot array {what} is malformed (need [{code!r}, shape, bytes])")
    shape = tuple(_typed(n, int, f"{what} shape") for n in v[1])
    dt = _DTYPES[code]
    if any(n < 0 for n in shape) or int(np.prod(shape, dtype=np.int64)) * dt.itemsize != len(v[2]):
        raise SnapshotError(f"snapshot array {what} has {len(v[2])} bytes for shape {shape}")
    return np.frombuffer(v[2], dtype=dt).reshape(shape).astype(dt.newbyteorder("="))


def _names(d: Any, what: str) -> dict:
    _typed(d, dict, what)
    for k in d:
        _typed(k, str, f"key of {what}")
    return d


def _ungraph(d: dict, what: str) -> GraphState:
    arrays = {name: _unarr(d[name], code, f"{what}.{name}") for name, code in _GRAPH_FIELDS}
    return GraphState(float(_typed(d["mr"], (int, float), f"{what}.mr")),
                      float(_typed(d["cm"], (int, float), f"{what}.cm")), _typed(d["next"], int, f"{what}.next"),
                      **arrays)  # fmt: skip


def _closure_dict(c: dict) -> dict:
    """A match record's closure entry: every required key, and the optional ones it has."""
    return {k: c[k] for k in _CLOSURE_KEYS} | {k: c[k] for k in _OPTIONAL_CLOSURE_KEYS if k in c}


def _unmatch(d: dict) -> MatchRecord:
    stored = _typed(d["cl"], list, "match closures")
    cl = [_closure_dict(c) for c in stored]
    for c in cl:
        _typed(c["reason"], str, "closure reason")
        _typed(c["accepted"], bool, "closure accepted")
        pair = _typed(c.get("stretches"), (list, type(None)), "closure stretches")
        if pair is not None and (len(pair) != 2 or not all(type(i) is int for i in pair)):
            raise SnapshotError(f"closure stretches must be two integers, got {pair!r}")
    opt_int = (int, type(None))
    return MatchRecord(
        _typed(d["step"], int, "match step"), _typed(d["a"], str, "match robot_a"),
        _typed(d["b"], str, "match robot_b"),
        _typed(d["q"], str, "match query"), _typed(d["ok"], bool, "match success"),
        _typed(d["acc"], bool, "match accepted"), _typed(d["why"], str, "match reason"),
        _typed(d["ka"], opt_int, "match kf_a"), _typed(d["kb"], opt_int, "match kf_b"),
        None if d["T"] is None else _unarr(d["T"], "f8", "match T_a_b").reshape(4, 4),
        _unarr(d["inl"], "i8", "match inliers").reshape(-1, 2), _typed(d["cand"], int, "match candidates"),
        _typed(d["na"], int, "match nodes_a"), _typed(d["nb"], int, "match nodes_b"),
        {k: float(_typed(v, (int, float), "match timing")) for k, v in _names(d["ms"], "match timings").items()},
        _unarr(d["pa"], "f8", "match positions a").reshape(-1, 3),
        _unarr(d["pb"], "f8", "match positions b").reshape(-1, 3),
        cl, _typed(d["dup"], bool, "match duplicate"),
        None if d.get("ev") is None else _unevidence(_names(d["ev"], "match evidence")),  # older snapshots: none
    )  # fmt: skip


def _unevidence(d: dict) -> MatchEvidence:
    num = (int, float)
    return MatchEvidence(
        _unarr(d["T"], "f8", "evidence T_a_b").reshape(4, 4), _typed(d["kb"], int, "evidence keyframe_b"),
        float(_typed(d["llr"], num, "evidence llr")), float(_typed(d["thr"], num, "evidence llr_threshold")),
        _typed(d["sup"], int, "evidence support"), float(_typed(d["ch"], num, "evidence expected_chance")),
        _typed(d["oa"], int, "evidence overlap_a"), _typed(d["ob"], int, "evidence overlap_b"),
        float(_typed(d.get("rl", -math.inf), num, "evidence rival_llr")),  # older snapshots: none recorded
        float(_typed(d.get("cs", math.nan), num, "evidence centroid_sigma_m")),  # older snapshots: none recorded
    )  # fmt: skip


def _unclosure(d: dict) -> ClosureRecord:
    return ClosureRecord(
        _typed(d["id"], int, "closure id"), _typed(d["a"], str, "closure robot_a"),
        _typed(d["ka"], int, "closure kf_a"),
        _typed(d["b"], str, "closure robot_b"), _typed(d["kb"], int, "closure kf_b"),
        _unarr(d["T"], "f8", "closure T_a_b").reshape(4, 4), _typed(d["n"], int, "closure inliers"),
        ClosureStatus(d["st"]), _typed(d["why"], str, "closure reason"), _typed(d["in"], bool, "closure in_graph"),
        _typed(d["mid"], (int, type(None)), "closure match_id"),
        _typed(d.get("q"), (str, type(None)), "closure querier"),  # absent in snapshots before it existed
        _typed(d.get("dec", False), bool, "closure decisive"),  # absent in snapshots before it existed
    )  # fmt: skip


def _unpose_graph(d: dict) -> PoseGraphState:
    anchors = {}
    for n, (cid, T) in _names(d["anchors"], "anchors").items():
        anchors[n] = (_typed(cid, (int, type(None)), "anchor closure"), _unarr(T, "f8", "anchor pose").reshape(4, 4))
    pairs = {}
    for a, b, v in _typed(d["pairs"], list, "pairs"):
        pairs[(_typed(a, str, "pair robot"), _typed(b, str, "pair robot"))] = PairVote(
            _unarr(v["ids"], "i8", "vote ids"), _unarr(v["A"], "b1", "vote adjacency"),
            _unarr(v["w"], "f8", "vote weights"), _unarr(v["ch"], "b1", "vote chosen"),
            _typed(v["exact"], bool, "vote exact"), _typed(v["n"], int, "vote searches"),
        )  # fmt: skip
    return PoseGraphState(
        tuple(_typed(r, str, "pose graph robot") for r in _typed(d["robots"], list, "pose graph robots")),
        anchors, {n: _unarr(T, "f8", f"estimate of {n}") for n, T in _names(d["est"], "estimate").items()},
        tuple(_unclosure(c) for c in _typed(d["closures"], list, "closures")), _unarr(d["info"], "f8", "information"),
        pairs, _typed(d["rebuilds"], int, "rebuilds"), _typed(d["recoveries"], int, "recoveries"),
        Factorization(d["fact"]),
        {n: _unarr(u, "f8", f"ground normals of {n}").reshape(-1, 3)
         for n, u in _names(d.get("up", {}), "normals").items()},
    )  # fmt: skip


def _unmap(d: dict) -> MapServerState:
    ups = _names(d["up"], "up")
    return MapServerState(
        tuple(_typed(a, str, "agent") for a in _typed(d["agents"], list, "agents")),
        {a: _ungraph(_names(g, f"graph {a}"), f"graph {a}") for a, g in _names(d["graphs"], "graphs").items()},
        {a: _unarr(T, "f8", f"keyframes of {a}") for a, T in _names(d["T"], "keyframes").items()},
        {a: None if u is None else _unarr(u, "f8", f"up of {a}") for a, u in ups.items()},
        {a: _typed(n, int, "since_match") for a, n in _names(d["since"], "since_match").items()},
        tuple(_unmatch(_names(m, "match")) for m in _typed(d["matches"], list, "matches")),
        tuple((_typed(a, str, "closure key"), _typed(i, int, "closure key"), _typed(b, str, "closure key"),
               _typed(j, int, "closure key")) for a, i, b, j in _typed(d["closures"], list, "closure keys")),
        _typed(d["step"], int, "step"), _typed(d["nm"], int, "num_matches"),
        {k: _unarr(v, "f8", f"timings {k}").tolist() for k, v in _names(d["ms"], "timings").items()},
        _unpose_graph(_names(d["pg"], "pose graph")),
        _unsupport(d),
        _surface_offset(d.get("offset", [0.0, 0.0, 0.0])),
    )  # fmt: skip


def _unsupport(d: dict) -> dict[int, dict[str, frozenset[int]]]:
    """``_support`` back; a snapshot written before "support_sets" holds each closure's objects in place."""
    sets = [_objects(sup) for sup in _typed(d.get("support_sets", []), list, "support sets")]
    out = {}
    for row in _typed(d.get("support", []), list, "support"):
        if len(_typed(row, list, "support row")) != 2:
            raise SnapshotError(f"snapshot: a support row must be [closure id, objects], got {row!r}")
        cid, sup = _typed(row[0], int, "support closure id"), row[1]
        if isinstance(sup, dict):
            out[cid] = _objects(sup)
            continue
        k = _typed(sup, int, "support set index")
        if not 0 <= k < len(sets):
            raise SnapshotError(f"snapshot: support set {k} of closure {cid} is not among {len(sets)} sets")
        out[cid] = sets[k]
    return out


def _objects(sup: object) -> dict[str, frozenset[int]]:
    """agent -> node ids, as ``_support`` writes one set."""
    return {
        a: frozenset(_typed(i, int, "support node id") for i in _typed(ids, list, "support node ids"))
        for a, ids in _names(sup, "support").items()
    }


def _surface_offset(v: object) -> tuple[float, float, float]:
    values = _typed(v, list, "surface offset")
    if len(values) != 3 or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in values):
        raise SnapshotError(f"snapshot: the surface offset must be three numbers, got {values!r}")
    return (float(values[0]), float(values[1]), float(values[2]))


def _unsession(d: dict) -> RobotSession:
    done = None
    if d["done"] is not None:
        done = decode(_typed(d["done"], bytes, "session done"))
        if not isinstance(done, DoneMessage):
            raise SnapshotError(f"snapshot session done holds a {type(done).__name__}")
    times = {a: _unarr(v, "f8", "keyframe times").tolist() for a, v in _names(d["t"], "keyframe times").items()}
    frames = {a: _unarr(v, "i8", "keyframe frames").tolist() for a, v in _names(d["f"], "keyframe frames").items()}
    return RobotSession(_typed(d["name"], str, "session name"), _typed(d["session"], str, "session id"),
                        RobotState(d["state"]), done=done, kf_timestamps=times, kf_frames=frames)  # fmt: skip


def decode_snapshot(body: bytes) -> ServerSnapshot:
    """Parse a snapshot body written by ``encode_snapshot``.

    Raises:
        SnapshotError: not msgpack, a missing key, or a field of the wrong type or shape.
    """
    try:
        d = _names(msgpack.unpackb(body, raw=False, strict_map_key=False, use_list=True, max_ext_len=0), "body")
        ref = d["reference"]
        return ServerSnapshot(
            _typed(d["records"], int, "records"), _typed(d["chain"], int, "chain"), _typed(d["config"], str, "config"),
            None if ref is None else _typed(ref, str, "reference"),
            tuple(_unsession(_names(s, "session")) for s in _typed(d["sessions"], list, "sessions")),
            None if d["map"] is None else _unmap(_names(d["map"], "map")),
        )  # fmt: skip
    except SnapshotError:
        raise
    except ShgmError as exc:  # a DoneMessage that does not decode
        raise SnapshotError(f"snapshot holds an unreadable message: {exc}") from None
    except (KeyError, TypeError, ValueError, IndexError, msgpack.UnpackException) as exc:
        raise SnapshotError(f"snapshot body is malformed ({type(exc).__name__}: {str(exc)[:80]})") from None
