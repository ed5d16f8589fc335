"""Key expressions of the shgm protocol, robot-name validation and Zenoh-style key matching.

Keys (one message kind each)::

    shgm/<robot>/hello        robot -> server   a robot announces itself (and what it has)
    shgm/<robot>/keyframe     robot -> server   one encoded keyframe message
    shgm/<robot>/done         robot -> server   the robot sent its last keyframe
    shgm/<robot>/correction   server -> robot   corrections for that robot
    shgm/server/status        server -> all     server status

The server subscribes with the wildcard forms (``shgm/*/keyframe``, ...). ``*`` matches exactly one
chunk and ``**`` any number of chunks, as in Zenoh. Robot names match
``[A-Za-z][A-Za-z0-9_-]{0,31}``, so they never contain Zenoh's reserved characters
(``/ * $ ? #``) and one name is always exactly one chunk. ``server`` is reserved.
"""

from __future__ import annotations

import re
from functools import lru_cache

from shgm_slam.errors import ConfigError

DEFAULT_PORT = 7447
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
"""Where the map server listens and robots connect when no endpoint is given (peer mode on loopback)."""

PREFIX = "shgm"
SERVER_NAME = "server"
STATUS_KEY = f"{PREFIX}/{SERVER_NAME}/status"

_ROBOT_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,31}")
_CHUNK = re.compile(r"[^/*$?#]+")


def validate_robot_name(robot: str) -> str:
    """Return ``robot`` unchanged if it is a valid robot name, else raise ConfigError."""
    if not isinstance(robot, str) or _ROBOT_NAME.fullmatch(robot) is None:
        raise ConfigError(
            f"robot name {robot!r} is invalid: use 1-32 characters, a letter first, then letters, "
            "digits, '_' or '-' (for example 'robot_a')"
        )
    if robot == SERVER_NAME:
        raise ConfigError(f"robot name {robot!r} is reserved for the map server; pick another name")
    return robot


def _robot_key(robot: str, kind: str) -> str:
    return f"{PREFIX}/{validate_robot_name(robot)}/{kind}"


def hello_key(robot: str) -> str:
    """``shgm/<robot>/hello``."""
    return _robot_key(robot, "hello")


def keyframe_key(robot: str) -> str:
    """``shgm/<robot>/keyframe``."""
    return _robot_key(robot, "keyframe")


def done_key(robot: str) -> str:
    """``shgm/<robot>/done``."""
    return _robot_key(robot, "done")


def correction_key(robot: str) -> str:
    """``shgm/<robot>/correction``."""
    return _robot_key(robot, "correction")


ALL_HELLO = f"{PREFIX}/*/hello"
ALL_KEYFRAMES = f"{PREFIX}/*/keyframe"
ALL_DONE = f"{PREFIX}/*/done"
ALL_CORRECTIONS = f"{PREFIX}/*/correction"
EVERYTHING = f"{PREFIX}/**"


def robot_of(key: str) -> str:
    """The robot name in a concrete ``shgm/<robot>/<kind>`` key (raises ConfigError otherwise)."""
    chunks = key.split("/")
    if len(chunks) != 3 or chunks[0] != PREFIX:
        raise ConfigError(f"key {key!r} is not of the form '{PREFIX}/<robot>/<kind>'")
    return validate_robot_name(chunks[1])


def validate_key_expr(key_expr: str, *, concrete: bool = False) -> str:
    """Check a key expression (``concrete=True``: no wildcards, as for publishing).

    Chunks are non-empty, separated by single ``/``; a chunk is ``*``, ``**`` or text without
    ``/ * $ ? #``. Raises ConfigError with the offending expression otherwise.
    """
    if not isinstance(key_expr, str) or not key_expr:
        raise ConfigError(f"key expression {key_expr!r} is empty")
    for chunk in key_expr.split("/"):
        wildcard = chunk in ("*", "**")
        if wildcard and concrete:
            raise ConfigError(f"cannot publish on {key_expr!r}: a publication key has no wildcards")
        if not wildcard and _CHUNK.fullmatch(chunk) is None:
            raise ConfigError(
                f"key expression {key_expr!r} is invalid: chunks are non-empty, separated by one '/', "
                "and are '*', '**' or text without '/', '*', '$', '?', '#'"
            )
    return key_expr


@lru_cache(maxsize=1024)
def key_matches(key_expr: str, key: str) -> bool:
    """Whether the concrete ``key`` matches ``key_expr`` (``*`` = one chunk, ``**`` = any chunks)."""
    pattern = key_expr.split("/")
    chunks = key.split("/")
    # reachable[j]: pattern[:i] can match chunks[:j]; one row per pattern chunk (O(P*K)).
    reachable = [True] + [False] * len(chunks)
    for part in pattern:
        if part == "**":
            nxt = list(reachable)
            for j in range(1, len(chunks) + 1):
                nxt[j] = nxt[j] or nxt[j - 1]
        else:
            nxt = [False] * (len(chunks) + 1)
            for j in range(1, len(chunks) + 1):
                nxt[j] = reachable[j - 1] and (part == "*" or part == chunks[j - 1])
        reachable = nxt
    return reachable[-1]
