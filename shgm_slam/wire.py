"""The wire codec of ``shgm_slam.messages``: versioned, compact msgpack bytes, and back (never pickle).

A payload is one msgpack map, the envelope ``{"v": PROTOCOL_VERSION, "k": MessageKind, ...fields}``
with 1-2 character field keys. Arrays travel as raw little-endian bytes whose dtype and shape the
schema fixes (the count N follows from the byte length, and must agree across columns):

- poses: the top 3 rows of a 4x4 pose, (3, 4) float64 (the bottom row [0, 0, 0, 1] is implied);
- node states (``GraphUpdate.new_nodes`` / ``updated_nodes``) column-wise: ids int64, labels uint8
  (Cityscapes train ids 0..18: a node is an object of a class), anchor keyframes int32 (at most the keyframe's
  own index, which is also the graph update's ``kf_id``), positions (N, 3) float32
  (metres in a keyframe camera frame: float32 keeps ~0.1 mm at 1 km), sizes float32 (pixel counts,
  exact below 2^24), observation counts uint16 (saturated at 65535 when encoding);
- ``up_odom`` (3,) float64 unit vector or nil (the keyframe's own ground normal; version 1 sent a running mean); per
  agent of a ``CorrectionMessage``: ``T_shared_odom`` one pose or nil, the keyframe count, keyframe
  indices int32 and their poses (M, 3, 4) float64, ``T_move`` one pose or nil;
- ``RobotTrajectory``: timestamps float64, segments int32, poses (N, 3, 4) float64 (a frame in no
  segment is all-NaN and comes back as an all-NaN 4x4).

Decoding trusts nothing: size bounds, the envelope, every field's presence and type, byte lengths,
finite numbers, orthonormal rotations, agent and session names, index ranges. Every violation, in
``encode`` as in ``decode``, raises ``WireError`` with a one-line message. Positions and sizes come back
at float32 precision, everything else exactly; since the in-process run goes through this codec too,
both runs see identical values.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from enum import IntEnum
from typing import Any

import msgpack
import numpy as np

from shgm_slam.errors import ProtocolError
from shgm_slam.graph.semantic_graph import GraphUpdate, NodeState
from shgm_slam.labels import NUM_CLASSES
from shgm_slam.messages import (
    AgentCorrection,
    CorrectionMessage,
    DoneMessage,
    HelloMessage,
    KeyframeMessage,
    Message,
    RobotState,
    RobotStatus,
    RobotTrajectory,
    StatusMessage,
)

PROTOCOL_VERSION = 4
"""Version of the payload layout; a peer with another version is refused (``WireError``). 2: corrections
carry only what changed (``AgentCorrection``), hellos a resync request, keyframes their own ground normal.
3: hellos carry the robot's sequence start and progress (the map server orders keyframes by time).
4: hellos carry the digest of the robot's front-end settings, dones its data-derived settings."""

MAX_PAYLOAD_BYTES = 16 * 1024 * 1024
"""Largest payload ``decode`` reads (and ``encode`` writes)."""

MAX_AGENTS = 4096
"""Most entries of any per-agent / per-robot map or list in a message."""

MAX_NODES = 4096
"""Most node states in each of a keyframe's new and updated nodes: an image holds at most ``1 / min_blob_fraction``
objects (some 120 by default, 700 at 100 m range); a map server fed tens of thousands at once ran out of memory."""

MAX_TEXT_CHARS = 1024
"""Longest free-text string (a refusal reason)."""

ROTATION_TOL = 1e-5
"""Largest |R^T R - I| entry accepted for the rotation part of a pose."""

MAX_TRANSLATION_M = 1e8
"""Largest |translation| entry of a pose, and |coordinate| of a node position, accepted (metres): 100,000 km, far
beyond any robot's odometry, yet small enough that distances between such values stay finite."""

UNIT_TOL = 1e-3
"""Largest | |up| - 1 | accepted for a keyframe's ground normal ``up_odom`` (a unit vector)."""

_I32_MAX = 2**31 - 1
_U16_MAX = 2**16 - 1
_ROBOT_RE = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,31}")
_AGENT_RE = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,31}(?:#[1-9][0-9]{0,8})?")
_SESSION_RE = re.compile(r"[0-9A-Za-z_-]{0,64}")
_DIGEST_RE = re.compile(r"[0-9a-f]{0,64}")
_SETTING_RE = re.compile(r"[a-z][a-z0-9_]{0,63}")
MAX_SETTINGS = 256
"""Most stages, and fields per stage, of a done message's ``settings``."""
_POSE_BYTES = 12 * 8
_NODE_BYTES = {"i": 8, "l": 1, "a": 4, "p": 12, "z": 4, "o": 2}  # bytes per node of each column
_STATE_CODES = {RobotState.ACTIVE: 0, RobotState.STALE: 1, RobotState.DONE: 2}
_CODE_STATES = {v: k for k, v in _STATE_CODES.items()}


class WireError(ProtocolError):
    """A payload (or a message to encode) breaks the wire format: the one error this module raises."""


class MessageKind(IntEnum):
    """The ``"k"`` of the envelope: which message a payload holds."""

    HELLO = 1
    KEYFRAME = 2
    DONE = 3
    CORRECTION = 4
    STATUS = 5


# --- value checks (shared by encode and decode) -------------------------------------------------------


def _name(value: Any, what: str, pattern: re.Pattern[str], rule: str) -> str:
    if not isinstance(value, str) or pattern.fullmatch(value) is None:
        raise WireError(f"{what} {_short(value)} is invalid: {rule}")
    return value


def _robot(value: Any, what: str) -> str:
    return _name(value, what, _ROBOT_RE, "need a letter, then up to 31 letters, digits, '_' or '-'")


def _agent(value: Any, what: str) -> str:
    return _name(value, what, _AGENT_RE, "need a robot name, optionally followed by '#<segment>' (segment >= 1)")


def _session(value: Any, what: str) -> str:
    return _name(value, what, _SESSION_RE, "need at most 64 characters from [0-9A-Za-z_-]")


def _digest(value: Any, what: str) -> str:
    return _name(value, what, _DIGEST_RE, "need at most 64 lowercase hex digits")


def _settings(value: Any, what: str) -> dict[str, dict[str, float | int | bool]] | None:
    """``{stage: {field: number or bool}}`` (names lowercase identifiers, numbers finite), or None."""
    if value is None:
        return None
    if not isinstance(value, Mapping) or len(value) > MAX_SETTINGS:
        raise WireError(f"{what} must be a map of at most {MAX_SETTINGS} stages")
    out: dict[str, dict[str, float | int | bool]] = {}
    for stage, fields in value.items():
        _name(stage, f"{what} stage", _SETTING_RE, "need a lowercase identifier")
        if not isinstance(fields, Mapping) or len(fields) > MAX_SETTINGS:
            raise WireError(f"{what}[{stage}] must be a map of at most {MAX_SETTINGS} fields")
        out[stage] = {}
        for name, v in fields.items():
            _name(name, f"{what}[{stage}] field", _SETTING_RE, "need a lowercase identifier")
            where = f"{what}[{stage}][{name}]"
            if isinstance(v, bool):
                out[stage][name] = v
            elif type(v) is int or isinstance(v, np.integer):
                out[stage][name] = _int(v, where, -_I32_MAX)
            else:
                out[stage][name] = _float(v, where)
    return out


def _int(value: Any, what: str, lo: int = 0, hi: int = _I32_MAX) -> int:
    if type(value) is not int and not isinstance(value, np.integer):
        raise WireError(f"{what} must be an integer, got {type(value).__name__}")
    value = int(value)
    if not lo <= value <= hi:
        raise WireError(f"{what} = {value} is out of range [{lo}, {hi}]")
    return value


def _float(value: Any, what: str) -> float:
    if type(value) not in (int, float) and not isinstance(value, np.floating | np.integer):
        raise WireError(f"{what} must be a number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise WireError(f"{what} must be finite, got {value}")
    return value


def _progress(value: Any) -> float:
    value = _float(value, "hello progress_s")
    if value < 0:
        raise WireError(f"hello progress_s must be >= 0 s, got {value}")
    return value


def _text(value: Any, what: str) -> str:
    if not isinstance(value, str) or len(value) > MAX_TEXT_CHARS or not value.isprintable():
        raise WireError(f"{what} must be one printable line of at most {MAX_TEXT_CHARS} characters")
    return value


def _bool(value: Any, what: str) -> bool:
    if not isinstance(value, bool):
        raise WireError(f"{what} must be true or false, got {type(value).__name__}")
    return value


def _short(value: Any) -> str:
    r = repr(value)
    return r if len(r) <= 60 else r[:57] + "..."


def _check_poses34(P: np.ndarray, what: str, allow_nan_rows: bool = False) -> None:
    """Check (N, 3, 4) float64 pose tops: finite with orthonormal, right-handed rotations (all-NaN rows ok
    when ``allow_nan_rows``)."""
    finite = np.isfinite(P).all(axis=(1, 2))
    if allow_nan_rows:
        bad = ~finite & ~np.isnan(P).all(axis=(1, 2))
        if bad.any():
            raise WireError(f"{what} [{int(np.argmax(bad))}] is partly NaN/inf (need finite or all-NaN)")
    elif not finite.all():
        raise WireError(f"{what} [{int(np.argmin(finite))}] has NaN or infinite entries")
    far = np.abs(P[finite, :, 3]).max(axis=1, initial=0.0) > MAX_TRANSLATION_M
    if far.any():
        raise WireError(f"{what} [{int(np.flatnonzero(finite)[np.argmax(far)])}] translation is beyond "
                        f"{MAX_TRANSLATION_M:.0e} m (need metres of a robot's odometry)")  # fmt: skip
    R = P[finite, :, :3]
    if R.shape[0] == 0:
        return
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = (err > ROTATION_TOL) | (det <= 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise WireError(
            f"{what} [{i}] rotation is not orthonormal (max |R^T R - I| = {err[i]:.2e}, det = {det[i]:.3f}; "
            f"tolerance {ROTATION_TOL})"
        )


def _pack_poses(T: Any, what: str, allow_nan_rows: bool = False) -> bytes:
    """(N, 4, 4) poses -> raw (N, 3, 4) little-endian float64 bytes, after checking them."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise WireError(f"{what} is not a numeric pose array: {exc}") from None
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise WireError(f"{what} must have shape (N, 4, 4), got {T.shape}")
    nan_rows = np.isnan(T).all(axis=(1, 2)) if allow_nan_rows else np.zeros(len(T), bool)
    bottom = T[~nan_rows, 3]
    if not np.allclose(bottom, [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
        raise WireError(f"{what} bottom row must be [0, 0, 0, 1]")
    _check_poses34(T[:, :3], what, allow_nan_rows)
    return np.ascontiguousarray(T[:, :3], dtype="<f8").tobytes()


def _unpack_poses(raw: bytes, n: int, what: str, allow_nan_rows: bool = False) -> np.ndarray:
    """Raw (n, 3, 4) float64 bytes -> checked (n, 4, 4) float64 poses."""
    P = np.frombuffer(raw, dtype="<f8").reshape(n, 3, 4).astype(np.float64)
    _check_poses34(P, what, allow_nan_rows)
    T = np.zeros((n, 4, 4))
    T[:, :3] = P
    T[:, 3, 3] = 1.0
    if allow_nan_rows:
        T[np.isnan(P).all(axis=(1, 2))] = np.nan
    return T


def _up(value: Any) -> np.ndarray:
    """A keyframe's ground normal ``up_odom``: a finite (3,) unit vector (within ``UNIT_TOL``)."""
    u = np.asarray(value, dtype=np.float64)
    if u.shape != (3,) or not np.isfinite(u).all():
        raise WireError(f"keyframe up_odom must be a finite (3,) vector, got shape {u.shape}")
    norm = float(np.sqrt(np.sum(u * u)))
    if abs(norm - 1.0) > UNIT_TOL:
        raise WireError(f"keyframe up_odom must be a unit vector (the ground normal), its length is {norm:.3g}")
    return u


def _check_update_indices(kf_index: int, update: GraphUpdate) -> None:
    """A keyframe's graph update is that keyframe's (``kf_id == kf_index``), and its nodes are anchored to it or to
    an earlier keyframe of the agent: what the map server relies on to apply it (robots send them in order)."""
    if update.kf_id != kf_index:
        raise WireError(f"keyframe {kf_index} carries the graph update of keyframe {update.kf_id}; they must agree")
    late = [s for s in (*update.new_nodes, *update.updated_nodes) if s.anchor_kf > kf_index]
    if late:
        raise WireError(
            f"keyframe {kf_index}: node {late[0].node_id} is anchored to keyframe {late[0].anchor_kf}, after it "
            "(nodes are anchored to the keyframe that first saw them)"
        )


# --- decoding helpers -------------------------------------------------------------------------------


class _Fields:
    """Typed, checked access to one msgpack map; ``close`` refuses keys nobody read."""

    def __init__(self, value: Any, what: str, keys: tuple[str, ...]):
        if not isinstance(value, dict):
            raise WireError(f"{what} must be a map, got {type(value).__name__}")
        extra = set(value) - set(keys)
        missing = [k for k in keys if k not in value]
        if extra or missing:
            raise WireError(
                f"{what} has fields {sorted(map(str, value))}, expected {sorted(keys)}"
                f" (missing {missing}, unknown {sorted(map(str, extra))})"
            )
        self.d = value
        self.what = what

    def name(self, key: str) -> str:
        return f"{self.what}.{key}"

    def raw(self, key: str, item_bytes: int, n: int | None = None, nullable: bool = False) -> bytes | None:
        """Bytes of key; their length must be a multiple of ``item_bytes`` (exactly n items if given)."""
        v = self.d[key]
        if v is None and nullable:
            return None
        if not isinstance(v, bytes):
            raise WireError(f"{self.name(key)} must be bytes, got {type(v).__name__}")
        if len(v) % item_bytes or (n is not None and len(v) != n * item_bytes):
            want = f"{n} x {item_bytes}" if n is not None else f"a multiple of {item_bytes}"
            raise WireError(f"{self.name(key)} has {len(v)} bytes, expected {want}")
        return v

    def map(self, key: str, check_key: Callable[[Any, str], Any]) -> dict:
        v = self.d[key]
        if not isinstance(v, dict):
            raise WireError(f"{self.name(key)} must be a map, got {type(v).__name__}")
        if len(v) > MAX_AGENTS:
            raise WireError(f"{self.name(key)} has {len(v)} entries, at most {MAX_AGENTS} allowed")
        for k in v:
            check_key(k, f"key of {self.name(key)}")
        return v


def _node_columns(nodes: tuple[NodeState, ...], what: str) -> dict[str, bytes]:
    n = len(nodes)
    if n > MAX_NODES:
        raise WireError(f"{what}: {n} node states, at most {MAX_NODES} per keyframe allowed")
    if n == 0:
        return {k: b"" for k in _NODE_BYTES}
    try:
        ids = np.array([s.node_id for s in nodes], dtype=object)
        labels = np.array([s.label_id for s in nodes], dtype=np.int64)
        anchors = np.array([s.anchor_kf for s in nodes], dtype=np.int64)
        pos = np.array([s.position_kf for s in nodes], dtype=np.float64).reshape(n, 3)
        sizes = np.array([s.size for s in nodes], dtype=np.float64)
        nobs = np.array([s.num_observations for s in nodes], dtype=np.int64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise WireError(f"{what}: node states are not numeric ({exc})") from None
    if any(not (-(2**63) <= int(i) < 2**63) for i in ids):
        raise WireError(f"{what}: node ids must fit in int64")
    if ((labels < 0) | (labels >= NUM_CLASSES)).any():
        raise WireError(f"{what}: label ids must be Cityscapes train ids 0..{NUM_CLASSES - 1}, got "
                        f"{labels.min()}..{labels.max()}")  # fmt: skip
    if ((anchors < 0) | (anchors > _I32_MAX)).any():
        raise WireError(f"{what}: anchor keyframes must be 0..{_I32_MAX}")
    with np.errstate(over="ignore"):  # too large for float32 -> inf, refused just below
        pos32, sizes32 = pos.astype("<f4"), sizes.astype("<f4")
    if not (np.isfinite(pos32).all() and np.isfinite(sizes32).all()) or (sizes32 < 0).any():
        raise WireError(f"{what}: node positions and sizes must be finite float32 values (sizes >= 0)")
    if (np.abs(pos32) > MAX_TRANSLATION_M).any():
        raise WireError(f"{what}: node positions must be within {MAX_TRANSLATION_M:.0e} m")
    return {
        "i": np.array(ids.astype(np.int64), dtype="<i8").tobytes(),
        "l": labels.astype("u1").tobytes(),
        "a": anchors.astype("<i4").tobytes(),
        "p": pos32.tobytes(),
        "z": sizes32.tobytes(),
        "o": np.clip(nobs, 0, _U16_MAX).astype("<u2").tobytes(),
    }


def _node_states(value: Any, what: str) -> tuple[NodeState, ...]:
    f = _Fields(value, what, tuple(_NODE_BYTES))
    raw_ids = f.raw("i", _NODE_BYTES["i"])
    n = len(raw_ids) // _NODE_BYTES["i"]
    if n > MAX_NODES:
        raise WireError(f"{what}: {n} node states, at most {MAX_NODES} per keyframe allowed")
    cols = {k: f.raw(k, b, n) for k, b in _NODE_BYTES.items()}
    ids = np.frombuffer(cols["i"], "<i8").tolist()
    labels_arr = np.frombuffer(cols["l"], "u1")
    anchors = np.frombuffer(cols["a"], "<i4")
    pos = np.frombuffer(cols["p"], "<f4").reshape(n, 3)
    sizes = np.frombuffer(cols["z"], "<f4")
    nobs = np.frombuffer(cols["o"], "<u2").tolist()
    if (labels_arr >= NUM_CLASSES).any():
        raise WireError(f"{what}: label ids must be Cityscapes train ids 0..{NUM_CLASSES - 1}, got {labels_arr.max()}")
    if (anchors < 0).any():
        raise WireError(f"{what}: anchor keyframes must be >= 0")
    if not (np.isfinite(pos).all() and np.isfinite(sizes).all()) or (sizes < 0).any():
        raise WireError(f"{what}: node positions and sizes must be finite (sizes >= 0)")
    if (np.abs(pos) > MAX_TRANSLATION_M).any():
        raise WireError(f"{what}: node positions must be within {MAX_TRANSLATION_M:.0e} m")
    labels, pos_list, size_list, anchor_list = labels_arr.tolist(), pos.tolist(), sizes.tolist(), anchors.tolist()
    return tuple(
        NodeState(ids[i], labels[i], anchor_list[i], tuple(pos_list[i]), size_list[i], nobs[i]) for i in range(n)
    )


def _trajectory_fields(tr: RobotTrajectory) -> dict[str, bytes]:
    t = np.asarray(tr.timestamps_s, dtype=np.float64).reshape(-1)
    seg = np.asarray(tr.frame_segment).reshape(-1)
    n = t.shape[0]
    if seg.shape[0] != n or np.shape(tr.T_odom_cam) != (n, 4, 4):
        raise WireError(
            f"trajectory arrays disagree: {n} timestamps, {seg.shape[0]} segments, poses {np.shape(tr.T_odom_cam)}"
        )
    if not np.isfinite(t).all():
        raise WireError("trajectory timestamps must be finite")
    if n and (seg.min() < -1 or seg.max() > _I32_MAX):
        raise WireError("trajectory segments must be -1 (none) or 0..2^31-1")
    return {"t": t.astype("<f8").tobytes(), "g": seg.astype("<i4").tobytes(),
            "T": _pack_poses(tr.T_odom_cam, "trajectory T_odom_cam", allow_nan_rows=True)}  # fmt: skip


def _trajectory(value: Any) -> RobotTrajectory:
    f = _Fields(value, "trajectory", ("t", "g", "T"))
    n = len(f.raw("t", 8)) // 8
    t = np.frombuffer(f.raw("t", 8), "<f8").astype(np.float64)
    seg = np.frombuffer(f.raw("g", 4, n), "<i4").astype(np.int64)
    T = _unpack_poses(f.raw("T", _POSE_BYTES, n), n, "trajectory T_odom_cam", allow_nan_rows=True)
    if not np.isfinite(t).all():
        raise WireError("trajectory timestamps must be finite")
    if (seg < -1).any():
        raise WireError("trajectory segments must be >= -1")
    return RobotTrajectory(t, seg, T)


def _agent_correction_fields(c: AgentCorrection, what: str) -> dict[str, Any]:
    if not isinstance(c, AgentCorrection):
        raise WireError(f"{what} must be an AgentCorrection")
    n = _int(c.num_keyframes, f"{what} num_keyframes")
    idx = np.asarray(c.kf_indices).reshape(-1)
    if c.T_shared_odom is None and (n or idx.size):
        raise WireError(f"{what}: an agent that is not placed carries no keyframes")
    if idx.size and (not np.issubdtype(idx.dtype, np.integer) or idx[0] < 0 or idx[-1] >= n
                     or (np.diff(idx) <= 0).any()):  # fmt: skip
        raise WireError(f"{what}: keyframe indices must increase within 0..{n - 1}")
    odom = None if c.T_shared_odom is None else _pack_poses(np.asarray(c.T_shared_odom)[None], f"{what} T_shared_odom")
    poses = np.asarray(c.T_shared_kf, dtype=np.float64).reshape(-1, 4, 4) if idx.size else np.zeros((0, 4, 4))
    if len(poses) != idx.size:
        raise WireError(f"{what}: {idx.size} keyframe indices but {len(poses)} poses")
    move = None if c.T_move is None else _pack_poses(np.asarray(c.T_move)[None], f"{what} T_move")
    if move is not None and odom is None:
        raise WireError(f"{what}: an agent that is not placed carries no keyframes")
    return {"o": odom, "K": n, "i": idx.astype("<i4").tobytes(), "T": _pack_poses(poses, f"{what} T_shared_kf"),
            "m": move}  # fmt: skip


def _agent_correction(value: Any, what: str) -> AgentCorrection:
    f = _Fields(value, what, ("o", "K", "i", "T", "m"))
    n = _int(f.d["K"], f"{what} num_keyframes")
    idx = np.frombuffer(f.raw("i", 4), "<i4").astype(np.int64)
    poses = _unpack_poses(f.raw("T", _POSE_BYTES, idx.size), idx.size, f"{what} T_shared_kf")
    raw_odom = f.raw("o", _POSE_BYTES, 1, nullable=True)
    if raw_odom is None and (n or idx.size):
        raise WireError(f"{what}: an agent that is not placed carries no keyframes")
    if idx.size and (idx[0] < 0 or idx[-1] >= n or (np.diff(idx) <= 0).any()):
        raise WireError(f"{what}: keyframe indices must increase within 0..{n - 1}")
    odom = None if raw_odom is None else _unpack_poses(raw_odom, 1, f"{what} T_shared_odom")[0]
    raw_move = f.raw("m", _POSE_BYTES, 1, nullable=True)
    if raw_move is not None and raw_odom is None:
        raise WireError(f"{what}: an agent that is not placed carries no keyframes")
    move = None if raw_move is None else _unpack_poses(raw_move, 1, f"{what} T_move")[0]
    return AgentCorrection(odom, n, idx, poses, move)


# --- encode -----------------------------------------------------------------------------------------


def _counts(d: Mapping[str, int], what: str, robot: str) -> dict[str, int]:
    if len(d) > MAX_AGENTS:
        raise WireError(f"{what} has {len(d)} agents, at most {MAX_AGENTS} allowed")
    out = {}
    for a, v in d.items():
        _own_agent(a, what, robot)
        out[a] = _int(v, f"{what}[{a}]")
    return out


def _own_agent(agent: Any, what: str, robot: str) -> str:
    _agent(agent, f"agent in {what}")
    if agent.partition("#")[0] != robot:
        raise WireError(f"{what} names agent {agent!r}, which is not an agent of robot {robot!r}")
    return agent


def _encode_fields(msg: Message) -> dict[str, Any]:
    if isinstance(msg, HelloMessage):
        return {"k": MessageKind.HELLO, "r": _robot(msg.robot, "hello robot"),
                "s": _session(msg.session, "hello session"), "n": _int(msg.num_frames, "hello num_frames"),
                "y": _bool(msg.resync, "hello resync"), "b": _float(msg.start_s, "hello start_s"),
                "p": None if msg.progress_s is None else _progress(msg.progress_s),
                "g": _session(msg.server_session, "hello server_session"),
                "d": _digest(msg.settings_digest, "hello settings_digest")}  # fmt: skip
    if isinstance(msg, KeyframeMessage):
        g = msg.graph_update
        T = np.asarray(msg.T_odom_kf, dtype=np.float64)
        T_world = np.asarray(g.T_world_kf, dtype=np.float64)
        up = None if msg.up_odom is None else _up(msg.up_odom).astype("<f8").tobytes()
        fields = {
            "k": MessageKind.KEYFRAME, "r": _agent(msg.robot, "keyframe robot"),
            "s": _session(msg.session, "keyframe session"), "i": _int(msg.kf_index, "keyframe kf_index"),
            "f": _int(msg.frame_index, "keyframe frame_index"), "t": _float(msg.timestamp_s, "keyframe timestamp_s"),
            "T": _pack_poses(T[None], "keyframe T_odom_kf"), "u": up, "gk": _int(g.kf_id, "graph update kf_id"),
            # the graph update's pose is nil when it is the keyframe pose (the usual case)
            "gT": None if np.array_equal(T, T_world) else _pack_poses(T_world[None], "graph update T_world_kf"),
            "gn": _node_columns(g.new_nodes, "new nodes"), "gu": _node_columns(g.updated_nodes, "updated nodes"),
        }  # fmt: skip
        _check_update_indices(fields["i"], g)  # (after the node states were checked)
        return fields
    if isinstance(msg, DoneMessage):
        robot = _robot(msg.robot, "done robot")
        return {"k": MessageKind.DONE, "r": robot, "s": _session(msg.session, "done session"),
                "c": _counts(msg.keyframes, "done keyframes", robot),
                "j": None if msg.trajectory is None else _trajectory_fields(msg.trajectory),
                "e": _settings(msg.settings, "done settings")}  # fmt: skip
    if isinstance(msg, CorrectionMessage):
        robot = _robot(msg.robot, "correction robot")
        if len(msg.agents) > MAX_AGENTS:
            raise WireError(f"correction has {len(msg.agents)} agents, at most {MAX_AGENTS}")
        agents = {_own_agent(a, "correction agents", robot): _agent_correction_fields(c, f"correction of {a}")
                  for a, c in msg.agents.items()}  # fmt: skip
        return {"k": MessageKind.CORRECTION, "r": robot, "s": _session(msg.session, "correction session"),
                "c": _counts(msg.received, "correction received", robot), "q": _int(msg.seq, "correction seq"),
                "F": _bool(msg.full, "correction full"), "A": agents}  # fmt: skip
    if isinstance(msg, StatusMessage):
        if len(msg.robots) > MAX_AGENTS or len(msg.refused) > MAX_AGENTS:
            raise WireError(f"status names more than {MAX_AGENTS} robots")
        robots = {}
        for r, st in msg.robots.items():
            _robot(r, "status robot")
            if not isinstance(st, RobotStatus) or st.state not in _STATE_CODES:
                raise WireError(f"status of robot {r!r} must be a RobotStatus with a RobotState")
            lists = [list(st.placed_agents), list(st.agents), list(st.provisional_agents), list(st.waiting_agents)]
            if any(len(x) > MAX_AGENTS for x in lists):
                raise WireError(f"status of robot {r!r} lists more than {MAX_AGENTS} agents")
            for x in lists:
                for a in x:
                    _agent(a, f"status agent of {r!r}")
            allowed = _int(st.segments_allowed, f"status segments allowed of {r!r}", 0, MAX_AGENTS)
            robots[r] = [_STATE_CODES[st.state], _int(st.keyframes, f"status keyframes of {r!r}"), *lists, allowed]
        refused = {_robot(r, "refused robot"): _text(why, f"refusal of {r!r}") for r, why in msg.refused.items()}
        reference = msg.reference if msg.reference == "" else _robot(msg.reference, "status reference")
        if not isinstance(msg.finished, bool):
            raise WireError("status finished must be a bool")
        return {"k": MessageKind.STATUS, "s": _session(msg.server_session, "status server_session"),
                "e": reference, "b": robots, "x": msg.finished, "y": refused}  # fmt: skip
    raise WireError(f"cannot encode {type(msg).__name__}: not a shgm_slam.messages message")


def encode(msg: Message) -> bytes:
    """Serialize one message into versioned msgpack bytes.

    Raises:
        WireError: the message breaks the schema (bad names, non-finite or non-rigid poses, values out
            of their wire range, too large).
    """
    fields = _encode_fields(msg)
    payload = msgpack.packb({"v": PROTOCOL_VERSION, **fields}, use_bin_type=True)
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise WireError(f"{type(msg).__name__} encodes to {len(payload)} bytes, over the {MAX_PAYLOAD_BYTES} limit")
    return payload


# --- decode -----------------------------------------------------------------------------------------

_KEYS = {
    MessageKind.HELLO: ("r", "s", "n", "y", "b", "p", "g", "d"),
    MessageKind.KEYFRAME: ("r", "s", "i", "f", "t", "T", "u", "gk", "gT", "gn", "gu"),
    MessageKind.DONE: ("r", "s", "c", "j", "e"),
    MessageKind.CORRECTION: ("r", "s", "c", "q", "F", "A"),
    MessageKind.STATUS: ("s", "e", "b", "x", "y"),
}


def _decode_fields(kind: MessageKind, f: _Fields) -> Message:
    d = f.d
    if kind is MessageKind.HELLO:
        return HelloMessage(_robot(d["r"], "hello robot"), _session(d["s"], "hello session"),
                            _int(d["n"], "hello num_frames"), _bool(d["y"], "hello resync"),
                            _float(d["b"], "hello start_s"), None if d["p"] is None else _progress(d["p"]),
                            _session(d["g"], "hello server_session"),
                            _digest(d["d"], "hello settings_digest"))  # fmt: skip
    if kind is MessageKind.KEYFRAME:
        T = _unpack_poses(f.raw("T", _POSE_BYTES, 1), 1, "keyframe T_odom_kf")[0]
        raw_world = f.raw("gT", _POSE_BYTES, 1, nullable=True)
        T_world = T.copy() if raw_world is None else _unpack_poses(raw_world, 1, "graph update T_world_kf")[0]
        raw_up = f.raw("u", 8, 3, nullable=True)
        up = None if raw_up is None else _up(np.frombuffer(raw_up, "<f8").astype(np.float64))
        update = GraphUpdate(_int(d["gk"], "graph update kf_id"), T_world,
                             _node_states(d["gn"], "new nodes"), _node_states(d["gu"], "updated nodes"))  # fmt: skip
        _check_update_indices(_int(d["i"], "keyframe kf_index"), update)
        return KeyframeMessage(
            _agent(d["r"], "keyframe robot"), _int(d["i"], "keyframe kf_index"), _int(d["f"], "keyframe frame_index"),
            _float(d["t"], "keyframe timestamp_s"), T, update, up, _session(d["s"], "keyframe session"),
        )  # fmt: skip
    if kind is MessageKind.DONE:
        robot = _robot(d["r"], "done robot")
        counts = f.map("c", lambda a, w: _own_agent(a, w, robot))
        traj = None if d["j"] is None else _trajectory(d["j"])
        return DoneMessage(robot, _session(d["s"], "done session"), _counts(counts, "done keyframes", robot), traj,
                           _settings(d["e"], "done settings"))  # fmt: skip
    if kind is MessageKind.CORRECTION:
        robot = _robot(d["r"], "correction robot")
        received = _counts(f.map("c", lambda a, w: _own_agent(a, w, robot)), "correction received", robot)
        agents = {a: _agent_correction(v, f"correction of {a}")
                  for a, v in f.map("A", lambda a, w: _own_agent(a, w, robot)).items()}  # fmt: skip
        return CorrectionMessage(robot, _session(d["s"], "correction session"), received,
                                 _int(d["q"], "correction seq"), _bool(d["F"], "correction full"), agents)  # fmt: skip
    # STATUS
    robots = {}
    for r, v in f.map("b", _robot).items():
        # the provisional (fifth) and waiting (sixth) agents and the segments allowed (seventh) came later: shorter
        # statuses of older servers are read
        if not (isinstance(v, list) and len(v) in (4, 5, 6, 7) and all(isinstance(x, list) for x in v[2:6])):
            raise WireError(
                f"status of robot {r!r} must be [state, keyframes, placed agents, agents, provisional agents, "
                "waiting agents, segments allowed]"
            )
        code = _int(v[0], f"status state of {r!r}", 0, len(_CODE_STATES) - 1)
        allowed = _int(v[6], f"status segments allowed of {r!r}", 0, MAX_AGENTS) if len(v) == 7 else 0
        placed, agents, provisional, waiting = (
            tuple(_agent(a, f"status agent of {r!r}") for a in x) for x in (*v[2:6], [], [])[:4]
        )
        robots[r] = RobotStatus(
            _CODE_STATES[code], _int(v[1], f"status keyframes of {r!r}"), placed, agents, provisional, waiting, allowed
        )
    refused = {r: _text(why, f"refusal of {r!r}") for r, why in f.map("y", _robot).items()}
    reference = d["e"] if d["e"] == "" else _robot(d["e"], "status reference")
    if not isinstance(d["x"], bool):
        raise WireError("status finished must be a bool")
    return StatusMessage(_session(d["s"], "status server_session"), reference, robots, d["x"], refused)


def decode(payload: bytes) -> Message:
    """Parse and check one payload from an untrusted peer.

    Args:
        payload: bytes made by ``encode`` (of this ``PROTOCOL_VERSION``), at most ``MAX_PAYLOAD_BYTES``.

    Returns:
        The message, equal field by field to the one encoded (positions and sizes at float32 precision).

    Raises:
        WireError: anything malformed, of another protocol version, or out of bounds.
    """
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise WireError(f"payload must be bytes, got {type(payload).__name__}")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise WireError(f"payload of {len(payload)} bytes is over the {MAX_PAYLOAD_BYTES}-byte limit")
    try:
        obj = msgpack.unpackb(
            payload, raw=False, strict_map_key=True, use_list=True, max_bin_len=MAX_PAYLOAD_BYTES,
            max_str_len=MAX_TEXT_CHARS * 4, max_array_len=MAX_AGENTS, max_map_len=MAX_AGENTS, max_ext_len=0,
        )  # fmt: skip
    except (ValueError, TypeError, OverflowError, RecursionError, msgpack.UnpackException) as exc:
        raise WireError(
            f"payload of {len(payload)} bytes is not one valid msgpack value ({_short(str(exc))})"
        ) from None
    if not isinstance(obj, dict):
        raise WireError(f"payload must be a msgpack map (the message envelope), got {type(obj).__name__}")
    version = obj.get("v")
    if version != PROTOCOL_VERSION or type(version) is not int:
        raise WireError(
            f"payload has protocol version {_short(version)}, this build speaks {PROTOCOL_VERSION}: "
            "run the same shgm_slam version on robots and server"
        )
    try:
        kind = MessageKind(obj.get("k"))
    except (ValueError, TypeError):
        raise WireError(f"payload has unknown message kind {_short(obj.get('k'))}") from None
    if type(obj.get("k")) is not int:
        raise WireError(f"payload message kind must be an integer, got {_short(obj.get('k'))}")
    fields = {k: v for k, v in obj.items() if k not in ("v", "k")}
    return _decode_fields(kind, _Fields(fields, f"{kind.name.lower()} message", _KEYS[kind]))
