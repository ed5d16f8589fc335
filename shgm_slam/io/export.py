"""Results folder of a run: trajectories evo reads, graphs, matches, the pose graph, config, metrics.

Layout of ``--out DIR`` (default ``results/<time>/`` plus a ``latest`` symlink)::

    <robot>_fused_tum.txt  <robot>_fused_kitti.txt   every localized robot in ONE shared frame (robot 0's)
    <robot>_odometry_tum.txt                          the robot's own odometry (its first camera frame)
    graph_<robot>.json                                shgm-graph/1, robot's odometry frame
    shared_graph_<robot>.json                         the same graph in the shared frame, while the robot is placed
                                                      (together: the fused semantic map)
    matches.json  pose_graph.g2o  config.yaml  metrics.json  run.rrd (when saving)
    server.json  journal.bin  snapshot-<records>.bin  queued.bin    a map server's metrics and crash recovery
    incomplete.txt                                    only when the run ended with an error: why (the rest is
                                                      its last checkpoint, not results; ``eval`` refuses it)

Every file is written atomically (temp file + rename) so an interrupted run never leaves half files.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from collections.abc import Callable, Iterable, Iterator
from datetime import datetime
from pathlib import Path
from typing import IO

import numpy as np

from shgm_slam.errors import ConfigError, DataError
from shgm_slam.io.graph_json import write_graph
from shgm_slam.io.json_text import to_json_text
from shgm_slam.io.trajectories import write_kitti_poses, write_tum
from shgm_slam.shared_frame import shared_frame_ground_truth
from shgm_slam.types import GraphArrays, Sequence

try:  # advisory file locks: POSIX; elsewhere two processes on one --out are not caught (no crash)
    import fcntl
except ImportError:  # pragma: no cover - not on Linux or macOS
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

LOCK_FILE = ".shgm-slam.lock"
"""Lock file in a results folder: held by the process writing the folder (its pid inside)."""

_held_locks: dict[Path, IO[str]] = {}
"""The results folders this process holds (resolved path -> open lock file)."""

RUN_OUTPUT_PATTERNS = (
    "*_fused_tum.txt", "*_fused_kitti.txt", "*_odometry_tum.txt", "*_gt_tum.txt", "*_gt_kitti.txt",
    "graph_*.json", "shared_graph_*.json", "matches.json", "pose_graph.g2o", "config.yaml", "metrics.json",
    "server.json", "run.rrd", "server.rrd", "journal.bin", "snapshot-*.bin", "queued.bin", "incomplete.txt",
)
"""Files a run, demo or map server writes into its results folder (``--overwrite`` removes these, and
their leftover ``.<name>.*`` temporary files, nothing else)."""


INCOMPLETE_FILE = "incomplete.txt"
"""Written into a results folder whose run ended with an error (``ResultsWriter.mark_incomplete``)."""
RERUN_ADVICE = "run it again with --overwrite"
"""What ``INCOMPLETE_FILE`` tells the user to do (a map server's folder: start the server on it again)."""


PROVISIONAL_COMMENT = "provisional:"
"""How the comment line of a provisional robot's fused trajectory files begins (``# provisional: why``)."""


RESUME_START_FILES = ("config.yaml", "server.rrd", "server.json")
"""What a map server writes before its journal exists; a folder holding only these is resumed too."""


def run_output_files(folder: Path) -> list[Path]:
    """The files in ``folder`` that a run, demo or map server wrote (``RUN_OUTPUT_PATTERNS``)."""
    found: set[Path] = set()
    for pattern in RUN_OUTPUT_PATTERNS:
        found.update(p for p in folder.glob(pattern) if p.is_file() or p.is_symlink())
        found.update(p for p in folder.glob(f".{pattern}.*") if p.is_file())  # temporaries of atomic writes
    return sorted(found)


def make_results_dir(
    out: Path | None, base: Path = Path("results"), *, overwrite: bool = False, resume_file: str | None = None
) -> Path:
    """Create the results folder: ``out`` if given, else a new ``base/<YYYYmmdd_HHMMSS>`` (``_2``, ``_3``, ... when
    a run of the same second took that name, in this process or another) plus ``base/latest``.

    The folder is locked for this process (``LOCK_FILE``; until ``release_results_dir`` or the process ends):
    a second run or map server on the same folder is refused instead of mixing its files into it.
    A reused ``out`` never mixes two runs' files: a folder holding files an earlier run wrote
    (``RUN_OUTPUT_PATTERNS``) is refused, unless ``overwrite`` (then those are removed first; other files
    are left alone) or ``resume_file`` names a file that is there (a map server's ``journal.bin``: the
    folder is resumed as it is; so is one holding only ``RESUME_START_FILES``).

    Raises:
        DataError: ``out`` is a file, cannot be created, is in use by another process, holds an earlier run's
            files (without ``overwrite``) or a folder where a run writes a file (``metrics.json/``: the run would
            fail at its first checkpoint or its end, ``overwrite`` or not), or one of those cannot be removed.
    """
    path = Path(out) if out is not None else _new_timed_dir(base)
    if path.exists() and not path.is_dir():
        raise DataError(f"results folder {path} is a file; choose a folder for --out")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DataError(f"cannot create results folder {path}: {exc.strerror}") from None
    _lock_results_dir(path)
    if out is not None:
        try:
            _claim_results_dir(path, overwrite=overwrite, resume_file=resume_file)
        except DataError:
            release_results_dir(path)
            raise
    if out is None:
        _point_latest(base, path)
    return path


def _new_timed_dir(base: Path) -> Path:
    """Create and return ``base/<YYYYmmdd_HHMMSS>`` for a run without ``--out``; when that folder exists (another
    run of the same second, in this process or another), ``<YYYYmmdd_HHMMSS>_2``, ``_3``, ...: two runs never
    share one (the second used to write into the first's folder, unchecked).

    Raises:
        DataError: the folder cannot be created.
    """
    stamp = datetime.now().strftime("%Y%m%d_%H%M%S")
    for n in range(1, 1000):
        path = base / (stamp if n == 1 else f"{stamp}_{n}")
        try:
            path.mkdir(parents=True)  # atomic: exactly one run creates it
            return path
        except FileExistsError:
            continue
        except OSError as exc:
            raise DataError(f"cannot create results folder {path}: {exc.strerror or exc}; pass --out") from None
    raise DataError(f"cannot create a new results folder in {base}: {base / stamp} and 998 more are taken; pass --out")


def _point_latest(base: Path, path: Path) -> None:
    """Point the ``base/latest`` symlink at ``path`` (atomically replaced); a warning when it cannot be (a
    folder of that name, no permission): the run goes on in ``path``."""
    latest, tmp = base / "latest", base / f".latest.{os.getpid()}"
    try:
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(path.name)
        os.replace(tmp, latest)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        log.warning("cannot point %s at %s: %s; the results are in %s", latest, path.name, exc.strerror or exc,
                    path)  # fmt: skip


@contextlib.contextmanager
def claimed_results_dir(out: Path | None, **options) -> Iterator[Path]:
    """``make_results_dir(out, **options)`` for the block; the folder's lock is released after it."""
    path = make_results_dir(out, **options)
    try:
        yield path
    finally:
        release_results_dir(path)


def _lock_results_dir(path: Path) -> None:
    """Hold ``path``'s ``LOCK_FILE`` for this process. Raises DataError when another process holds it (naming its
    pid), this process holds it already (a run or ``LiveRun`` in it has not finished: two in one process mixed
    their files, the second with ``overwrite`` removing the first's), or the file cannot be created."""
    key = path.resolve()
    if key in _held_locks:
        raise DataError(
            f"results folder {path} is in use by a run of this process that has not finished (a LiveRun not "
            "finished yet?); finish it first, or choose another --out"
        )
    if fcntl is None:
        return
    try:
        fh = open(path / LOCK_FILE, "a+")
    except OSError as exc:
        raise DataError(f"cannot write into results folder {path}: {exc.strerror}; choose another --out") from None
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.seek(0)
        holder = fh.read().strip() or "unknown"
        fh.close()
        raise DataError(
            f"results folder {path} is in use by another shgm-slam process (pid {holder}); wait for it to "
            "finish, or choose another --out"
        ) from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"{os.getpid()}\n")
    fh.flush()
    _held_locks[key] = fh


def results_dir_writer(path: Path) -> str | None:
    """The pid of another process that holds the results folder ``path`` now (``LOCK_FILE``: a ``run``, ``demo``
    or map server still writing it), else None (free, held by this process, or locks not supported)."""
    path = Path(path)
    if fcntl is None or path.resolve() in _held_locks:
        return None
    try:
        fh = open(path / LOCK_FILE)
    except OSError:
        return None  # no lock file: nobody writes the folder (a writer creates it before its first file)
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError:
            return fh.read().strip() or "unknown"
        fcntl.flock(fh, fcntl.LOCK_UN)
    return None


def check_writable_dir(path: Path) -> Path:
    """Create the folder ``path`` if needed and make sure a file can be written in it, before any work.

    Raises:
        DataError: it is a file, or cannot be created or written (read-only, no space, no permission).
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise DataError(f"output folder {path} is a file; choose a folder for --out")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".write-check-"):
            pass
    except OSError as exc:
        raise DataError(f"cannot write into {path}: {exc.strerror or exc}; choose another --out") from None
    return path


def check_outside_sequence(out: Path, root: Path, whose: str = "") -> None:
    """Refuse an output path that is the sequence folder ``root`` or lies inside it.

    Raises:
        ConfigError: it does (results or a graph file among the sequence's files, or over one of them).
    """
    target, root = Path(out).resolve(), Path(root).resolve()
    if target == root or root in target.parents:
        raise ConfigError(
            f"--out {out} is in the sequence folder {whose}({root}): writing there would change the sequence; "
            "choose a path outside it"
        )


def release_results_dir(path: Path) -> None:
    """Release this process's lock on the results folder ``path`` and remove its ``LOCK_FILE`` (nothing if it
    holds none)."""
    fh = _held_locks.pop(Path(path).resolve(), None)
    if fh is not None:
        with contextlib.suppress(OSError):  # the folder keeps only its results
            (Path(path) / LOCK_FILE).unlink()
        fh.close()  # closing drops the flock


SEQUENCE_MARKERS = ("calib.txt", "times.txt")
"""Files that make a folder a sequence (KITTI layout): results are never written among them."""


def _claim_results_dir(path: Path, *, overwrite: bool, resume_file: str | None) -> None:
    """Refuse ``path`` when it is a sequence folder or holds an earlier run's files, or clear those (see
    ``make_results_dir``)."""
    if all((path / name).is_file() for name in SEQUENCE_MARKERS):
        raise DataError(
            f"results folder {path} holds a sequence ({', '.join(SEQUENCE_MARKERS)}): results written there would "
            "mix with its files; choose another --out"
        )
    try:
        ours = run_output_files(path)
        blocking = sorted(p for pattern in RUN_OUTPUT_PATTERNS for p in path.glob(pattern)
                          if p.is_dir() and not p.is_symlink())  # fmt: skip
    except OSError as exc:
        raise DataError(f"cannot read results folder {path}: {exc.strerror}") from None
    if blocking:  # a results file cannot replace it: the run would fail at its first checkpoint, or at its end
        raise DataError(
            f"results folder {path} holds a folder named {blocking[0].name}, where a run writes that file; move "
            "it away or choose another --out"
        )
    if not ours:
        return  # empty, or only other files (logs, notes): nothing to mix with
    if overwrite:
        for old in ours:
            try:
                old.unlink()
            except OSError as exc:
                raise DataError(f"cannot remove {old} of an earlier run: {exc.strerror}") from None
        return
    if resume_file is not None:
        if (path / resume_file).is_file() or {p.name for p in ours} <= set(RESUME_START_FILES):
            return  # a journal to replay, or a server that stopped before hearing from any robot
    names = ", ".join(p.name for p in ours[:3]) + (", ..." if len(ours) > 3 else "")
    raise DataError(
        f"results folder {path} holds an earlier run's results ({names}); choose a new --out, or pass "
        "--overwrite to remove them first (other files are kept)"
    )


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_FILE_MODE = 0o666 & ~_umask()
"""Mode of results files: what ``open()`` would give (mkstemp's 0600 would hide results from other users)."""


def _raise_write_error(path: Path, exc: BaseException) -> None:
    """Raise DataError for an OS error writing ``path``; return for anything else (the caller re-raises it)."""
    if isinstance(exc, OSError):
        raise DataError(f"cannot write {path}: {exc.strerror or exc}; free space or choose another --out") from None


def _write_temp(path: Path, write: Callable[[Path], object]) -> Path:
    """Call ``write(tmp)`` on a new temporary file beside ``path`` (normal file mode) and return it.

    Raises:
        DataError: the folder is not writable or the disk is full (the temporary file is removed).
        KeyboardInterrupt: a stop signal arrived while writing (the temporary file is removed).
    """
    tmp = None
    try:
        fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
        tmp = Path(name)
        os.close(fd)
        write(tmp)
        os.chmod(tmp, _FILE_MODE)
        return tmp
    except BaseException as exc:  # a stop signal (KeyboardInterrupt) mid-write leaves no temporary either
        if tmp is not None:
            tmp.unlink(missing_ok=True)
        _raise_write_error(path, exc)
        raise


def _commit(tmp: Path, path: Path) -> None:
    """Rename the finished temporary ``tmp`` onto ``path`` (atomic: readers see the old or the new file)."""
    try:
        os.replace(tmp, path)
    except BaseException as exc:  # the rename did not happen (an error, or a stop signal just before it)
        tmp.unlink(missing_ok=True)
        _raise_write_error(path, exc)
        raise


def _atomic(path: Path, write: Callable[[Path], object]) -> None:
    """Write ``path`` through a temporary file and a rename: readers never see a half-written file, and an
    interrupted or failed write leaves the previous version intact.

    Raises:
        DataError: the folder is not writable or the disk is full (the previous file is kept).
    """
    _commit(_write_temp(path, write), path)


def _discard(batch: list[tuple[Path | None, Path]]) -> None:
    """Remove the temporaries of an unfinished checkpoint."""
    for tmp, _ in batch:
        if tmp is not None:
            tmp.unlink(missing_ok=True)


def _remove(path: Path) -> None:
    """Delete ``path`` if it is there; DataError when it cannot be removed."""
    try:
        path.unlink(missing_ok=True)
    except OSError as exc:
        raise DataError(f"cannot remove {path}: {exc.strerror or exc}; check the folder's permissions") from None


def _valid_rows(poses: np.ndarray) -> np.ndarray:
    return np.isfinite(poses.reshape(len(poses), 16)).all(axis=1)


class ResultsWriter:
    """Writes one run's outputs into ``root``; every method can be called again to overwrite.

    Each file is replaced atomically; inside ``with writer.checkpoint():`` the files written form one
    checkpoint, which replaces the previous one only once every file of it was written.
    """

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DataError(f"cannot create results folder {self.root}: {exc.strerror or exc}") from None
        self._batch: list[tuple[Path | None, Path]] | None = None  # (temporary or None to delete, target)

    def path(self, name: str) -> Path:
        return self.root / name

    @contextlib.contextmanager
    def checkpoint(self) -> Iterator[None]:
        """Collect the files written inside the block and put them in place together at its end.

        Every file is first written to a temporary beside it; only when all were written (no full disk,
        no error, no interruption) are they renamed onto the previous files, so a failure leaves the
        previous checkpoint whole rather than half old, half new.

        Raises:
            DataError: a file could not be written (the previous checkpoint is kept, no temporaries left).
        """
        if self._batch is not None:  # nested: part of the enclosing checkpoint
            yield
            return
        self._batch = []
        try:
            yield
        except BaseException:
            _discard(self._batch)
            raise
        finally:
            batch, self._batch = self._batch, None
        for i, (tmp, path) in enumerate(batch):
            try:
                if tmp is None:
                    _remove(path)
                else:
                    _commit(tmp, path)
            except BaseException:  # an error or a stop signal: the rest of the checkpoint leaves no temporaries
                _discard(batch[i + 1 :])
                raise

    def _put(self, path: Path, write: Callable[[Path], object]) -> None:
        """Write ``path`` atomically, or as part of the open checkpoint."""
        if self._batch is None:
            _atomic(path, write)
        else:
            self._batch.append((_write_temp(path, write), path))

    def _drop(self, path: Path) -> None:
        """Delete ``path`` now, or when the open checkpoint is put in place."""
        if self._batch is None:
            _remove(path)
        else:
            self._batch.append((None, path))

    def write_trajectories(
        self,
        robot: str,
        timestamps_s: np.ndarray,
        T_odom_cam: np.ndarray,
        T_shared_cam: np.ndarray | None,
        *,
        provisional: str | None = None,
    ) -> None:
        """Odometry (TUM) and, when the robot is localized, fused (TUM + KITTI) trajectories.

        Frames with NaN poses (skipped) are left out of TUM files; the KITTI file (no timestamps)
        holds only the frames that have a fused pose, in order. ``provisional`` (why the robot's place
        is not confirmed) becomes the fused TUM file's first line, ``# provisional: ...`` (TUM allows
        comments; evo skips it); the KITTI file stays plain 12-number rows, as KITTI's devkit reads them.
        A robot no longer placed loses the fused files an earlier checkpoint wrote.
        """
        ok = _valid_rows(T_odom_cam)
        self._put(self.path(f"{robot}_odometry_tum.txt"), lambda p: write_tum(p, timestamps_s[ok], T_odom_cam[ok]))
        tum, kitti = self.path(f"{robot}_fused_tum.txt"), self.path(f"{robot}_fused_kitti.txt")
        if T_shared_cam is None:
            for stale in (tum, kitti):
                self._drop(stale)
            return
        okf = _valid_rows(T_shared_cam)
        note = f"{PROVISIONAL_COMMENT} {provisional}" if provisional else ""
        self._put(tum, lambda p: write_tum(p, timestamps_s[okf], T_shared_cam[okf], comment=note))
        self._put(kitti, lambda p: write_kitti_poses(p, T_shared_cam[okf]))

    def write_keyframe_trajectory(
        self,
        robot: str,
        timestamps_s: np.ndarray,
        T_odom_kf: np.ndarray,
        T_shared_kf: np.ndarray | None,
        *,
        provisional: str | None = None,
    ) -> None:
        """Keyframe-rate trajectories of a robot whose per-frame odometry the writer does not have yet (a
        live map server before the robot's last message; ``write_trajectories`` replaces them later).

        Args:
            timestamps_s: (K,) keyframe times.
            T_odom_kf: (K, 4, 4) keyframes in the odometry frame of their own trajectory segment.
            T_shared_kf: (K, 4, 4) fused keyframes (NaN rows: segment not placed), or None.
            provisional: as for ``write_trajectories``.
        """
        self.write_trajectories(robot, timestamps_s, T_odom_kf, T_shared_kf, provisional=provisional)

    def write_graph(self, robot: str, graph: GraphArrays) -> None:
        self._put(self.path(f"graph_{robot}.json"), lambda p: write_graph(p, graph))

    def write_shared_graph(self, agent: str, graph: GraphArrays | None) -> None:
        """``shared_graph_<agent>.json``: the agent's graph in the shared frame (``MapServer.shared_graph``); an
        agent no longer placed loses the file an earlier checkpoint wrote."""
        path = self.path(f"shared_graph_{agent}.json")
        if graph is None:
            self._drop(path)
            return
        self._put(path, lambda p: write_graph(p, graph))

    def write_json(self, name: str, data: object) -> None:
        text = to_json_text(data) + "\n"  # strict JSON: NaN (not measurable) as null
        self._put(self.path(name), lambda p: p.write_text(text))

    def write_matches(self, records: Iterable) -> None:
        self.write_json("matches.json", [r.to_json_dict() for r in records])

    def write_text(self, name: str, text: str) -> None:
        self._put(self.path(name), lambda p: p.write_text(text))

    def mark_incomplete(self, reason: str, advice: str = RERUN_ADVICE) -> Path:
        """Say in ``INCOMPLETE_FILE`` that the run ended with an error (``reason``, one line) and what to do
        (``advice``): the files beside it are its last checkpoint, not its results. Returns the file's path."""
        path = self.path(INCOMPLETE_FILE)
        text = (f"this run ended with an error before its results were complete: {' '.join(reason.split())}\n"
                f"the other files here are its last checkpoint (no metrics.json); {advice}\n")
        _atomic(path, lambda p: p.write_text(text))
        return path

    def mark_failed(self, exc: Exception, advice: str = RERUN_ADVICE) -> None:
        """``mark_incomplete`` with the error ``exc`` that ended the run, and a log line saying so; only a log line
        when the folder cannot be written (``exc`` stays the error to report)."""
        try:
            path = self.mark_incomplete(f"{type(exc).__name__}: {exc}", advice)
        except DataError as marker_exc:
            log.warning("%s: cannot mark the unfinished results: %s", self.root, marker_exc)
            return
        log.warning("the run ended with an error; the files in %s are its last checkpoint, marked by %s (%s)",
                    self.root, path.name, advice)  # fmt: skip

    def clear_incomplete(self) -> None:
        """Remove ``INCOMPLETE_FILE`` (a restarted map server that finished on the folder of one that failed)."""
        self.path(INCOMPLETE_FILE).unlink(missing_ok=True)

    def write_bytes(self, name: str, data: bytes) -> None:
        """Write ``data`` atomically and durably (fsync'd before the rename: it survives a power loss too)."""

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())

        _atomic(self.path(name), write)

    def write_ground_truth(self, robots: dict[str, Sequence], gt_shared_frame: bool = True) -> list[Path]:
        """``<robot>_gt_tum.txt`` and ``<robot>_gt_kitti.txt``: ground truth in the shared frame.

        The frame of the fused trajectories (the first robot's first camera), so ``evo_ape tum
        <robot>_gt_tum.txt <robot>_fused_tum.txt`` needs no alignment. Robots without ground truth (or,
        when ``gt_shared_frame`` is False, every robot but the first) get no file. Returns the files written.
        """
        written = []
        for robot, T_shared_cam in shared_frame_ground_truth(robots, gt_shared_frame).items():
            t = np.asarray(robots[robot].timestamps_s)
            tum, kitti = self.path(f"{robot}_gt_tum.txt"), self.path(f"{robot}_gt_kitti.txt")
            self._put(tum, lambda p, t=t, T=T_shared_cam: write_tum(p, t, T))
            self._put(kitti, lambda p, T=T_shared_cam: write_kitti_poses(p, T))
            written += [tum, kitti]
        return written
