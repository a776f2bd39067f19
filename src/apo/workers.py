"""Work split over processes forked on the spot (the second core of a machine).

``apo analyze`` is one process and its target is wall time; on a machine with two or more
cores, the stages whose cost grows with the distinct frames (the contact search of every
frame, the correction of every frame) give parts of their frames to processes forked for
that stage: a forked child has every model, pose and state of its parent at no cost, computes
its part and sends it back through a pipe (pickled), then exits. Every part is computed by
the same functions as in one process, so the results are the same bit for bit
(``tests/test_workers.py``; ``docs/recognition.md``, "Session 5").

``apo analyze`` also reads a pose file and its models in a child while it imports the
recognition stages (:mod:`apo.cli.analyze`): this module imports only the standard library
and numpy, so that the fork comes before those imports.

Forking is done only where it is safe and pays: ``os.fork`` exists, the process runs a
single thread (a fork copies only the calling thread; a lock held by another one would stay
held in the child), and the caller has enough frames (``PARALLEL_MIN_FRAMES``). Otherwise,
or with ``jobs=1``, every part runs in the calling process, in order.
"""

from __future__ import annotations

import atexit
import mmap
import os
import pickle
import threading
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import numpy as np

__all__ = [
    "PARALLEL_MIN_FRAMES",
    "available_cores",
    "can_fork",
    "run_parts",
    "shared_zeros",
    "workers_for",
]

T = TypeVar("T")

#: Distinct frames from which a stage splits its frames over processes (auto ``jobs``): a
#: fork and the result's way back cost 2-5 ms, about what 30-60 frames of the contact search
#: cost; below this many frames the stage runs in one process.
PARALLEL_MIN_FRAMES = 768

#: Most processes a stage uses with ``jobs=None`` (auto), whatever the number of cores.
MAX_AUTO_JOBS = 4


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where known)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def workers_for(jobs: int | None, frames: int, *, min_frames: int = PARALLEL_MIN_FRAMES) -> int:
    """Return the number of processes a stage should use for ``frames`` distinct frames.

    ``jobs``: the user's choice (``--jobs``), at most one process per frame; None (auto):
    one process below ``min_frames`` frames, else the available cores up to
    ``MAX_AUTO_JOBS`` and one per ``min_frames // 2`` frames. Always 1 where forking is not
    possible or not safe (no ``os.fork``, several threads running).
    """
    if jobs is not None and jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    if jobs is None:
        if frames < min_frames:
            return 1
        want = min(available_cores(), MAX_AUTO_JOBS, frames // max(1, min_frames // 2))
    else:
        want = min(jobs, frames)
    return want if want > 1 and can_fork() else 1


def can_fork() -> bool:
    """Whether this process may fork workers: ``os.fork`` exists and one thread runs."""
    return hasattr(os, "fork") and threading.active_count() == 1


def run_parts(parts: Sequence[Callable[[], T]]) -> list[T]:
    """Return ``[p() for p in parts]``, the parts after the first computed by forked children.

    The calling process computes ``parts[0]`` while the children compute the others; each
    child sends its result back pickled and exits (``os._exit``: no ``atexit`` handler, no
    buffered output of the parent written twice). An exception in a child is raised again
    here; a child that died without a result has its part computed here.
    """
    if len(parts) <= 1:
        return [p() for p in parts]
    children = [_fork(p) for p in parts[1:]]
    try:
        first = parts[0]()
    finally:
        results = [_collect(pid, fd) for pid, fd in children]
    out: list[T] = [first]
    for part, (ok, value) in zip(parts[1:], results, strict=True):
        if ok is None:  # the child died without a word: compute its part here
            out.append(part())
        elif not ok:
            raise value
        else:
            out.append(value)
    return out


def _fork(part: Callable[[], Any]) -> tuple[int, int]:
    """Fork a child that computes ``part()`` and writes ``(True, result)`` to a pipe."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - runs in the child (its coverage is not collected)
        code = 0
        try:
            os.close(r)
            try:
                data = pickle.dumps((True, part()), protocol=pickle.HIGHEST_PROTOCOL)
            except BaseException as exc:  # handed to the parent
                data = pickle.dumps((False, exc), protocol=pickle.HIGHEST_PROTOCOL)
            with os.fdopen(w, "wb") as fh:
                fh.write(data)
        except BaseException:  # nothing to report: the parent recomputes
            code = 1
        finally:
            os._exit(code)
    os.close(w)
    return pid, r


def _collect(pid: int, fd: int) -> tuple[bool | None, Any]:
    """Read a child's result: ``(ok, value)``, ``(None, None)`` if it sent none.

    The child is reaped if it has exited; else later (:func:`_reap`): once its result is
    read (the end of the pipe), the parent does not wait while the child's memory is freed.
    The result is unpickled from the pipe as it comes (its arrays read into their own
    buffers), not read whole first: no copy of the message beside the arrays it holds.
    """
    with os.fdopen(fd, "rb") as fh:
        try:
            ok, value = pickle.load(fh)
        except Exception:  # no or a cut message: the parent computes it
            ok = None
    _UNREAPED.append(pid)
    _reap(block=False)
    if ok is None:
        return None, None
    return bool(ok), value


#: Children whose result was read but that had not exited yet (reaped by :func:`_reap`).
_UNREAPED: list[int] = []


def _reap(*, block: bool) -> None:
    """Reap the children in ``_UNREAPED`` that have exited (all of them with ``block``)."""
    for pid in list(_UNREAPED):
        try:
            done, _status = os.waitpid(pid, 0 if block else os.WNOHANG)
        except ChildProcessError:  # reaped elsewhere
            done = pid
        if done:
            _UNREAPED.remove(pid)
    if _UNREAPED and not _REAP_AT_EXIT:
        atexit.register(_reap, block=True)
        _REAP_AT_EXIT.append(True)


_REAP_AT_EXIT: list[bool] = []


def shared_zeros(shape: tuple[int, ...], dtype: Any, shared: bool) -> np.ndarray[Any, Any]:
    """Zeros of ``shape``; with ``shared``, in memory that forked children write into too.

    An anonymous ``MAP_SHARED`` mapping (``mmap.mmap(-1, ...)``): a child forked after it is
    made writes its part of the rows in place, and nothing is sent back or copied.
    """
    dt = np.dtype(dtype)
    if not shared:
        return np.zeros(shape, dtype=dt)
    size = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
    buf = mmap.mmap(-1, max(size, 1))
    return np.frombuffer(buf, dtype=dt, count=size // dt.itemsize).reshape(shape)
