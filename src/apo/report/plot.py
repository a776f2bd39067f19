"""PNG of the DOF indices over time (matplotlib, Agg backend, imported on use)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from apo.task import TaskModel
from apo.typing import FloatArray

__all__ = ["plot_dof"]

_COLORS = {
    "M": "#4c9be8",
    "D": "#f2a541",
    "C": "#d9534f",
    "SM": "#a6cdf5",
    "SD": "#f9d29d",
    "SC": "#eea6a4",
}
_KINDS = ("M", "D", "C", "SM", "SD", "SC")


def plot_dof(
    task: TaskModel,
    path: str | Path,
    *,
    times: npt.ArrayLike | None = None,
    title: str | None = None,
) -> Path:
    """Write a PNG of the translation and rotation DOF indices of each frame's state.

    Two stacked-area panels (translation, rotation), each showing M, D, C and the singular
    SM, SD, SC (lighter shades) summing to 3, with the state letters along the top and
    critical transitions marked by red vertical lines.

    Parameters
    ----------
    task : TaskModel
    path : str or Path
        Output PNG file.
    times : array_like, shape (n_frames,), optional
        Time stamps (s) of the frames; default: frame indices.
    title : str, optional

    Returns
    -------
    Path
        ``path``.
    """
    # The object-oriented API with the Agg canvas: no pyplot, no GUI backend, and no global
    # state (safe in threads and servers).
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n = max(task.n_frames, task.states[-1].frames[1] + 1 if task.states else 1)
    x = np.arange(n, dtype=float) if times is None else np.asarray(times, dtype=float)
    xlabel = "frame" if times is None else "time [s]"
    vals = {sp: np.zeros((6, n)) for sp in ("translation", "rotation")}
    for s in task.states:
        a, b = s.frames
        for sp in vals:
            six = s.six.get(sp)
            if six is None:
                continue
            vals[sp][:, a : b + 1] = np.asarray(six, dtype=float)[:, None]
    # One more edge so that the last frame gets its own width in the step plot.
    step = float(x[-1] - x[-2]) if n > 1 else 1.0
    x = np.r_[x, x[-1] + (step if step > 0 else 1.0)]
    vals = {sp: np.concatenate([v, v[:, -1:]], axis=1) for sp, v in vals.items()}
    fig = Figure(figsize=(10, 5.5))
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 1, sharex=True)
    for ax, sp in zip(axes, ("translation", "rotation"), strict=True):
        ax.stackplot(
            x,
            vals[sp],
            labels=list(_KINDS),
            colors=[_COLORS[k] for k in _KINDS],
            step="post",
        )
        ax.set_ylim(0, 3)
        ax.set_yticks([0, 1, 2, 3])
        ax.set_ylabel(f"{sp} DOF")
        _transition_lines(ax, task, x, n)
    _state_labels(axes[0], task, x)
    axes[0].legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8)
    axes[1].set_xlabel(xlabel)
    fig.suptitle(title or f"DOF indices: {task.source or 'demonstration'}", y=0.995)
    # fixed margins (room for the legend on the right): no layout pass before drawing
    fig.subplots_adjust(left=0.07, right=0.88, top=0.9, bottom=0.1, hspace=0.12)
    out = Path(path)
    fig.savefig(out, dpi=110, format="png")
    return out


#: At most this many state letters are written along the top (the widest states first).
MAX_LABELS = 40


def _transition_lines(ax: Any, task: TaskModel, x: FloatArray, n: int) -> None:
    """Draw every transition as a vertical line: two collections (ordinary, critical).

    One ``LineCollection`` per kind, so the cost does not grow per transition drawn.
    """
    xs = np.array([x[min(t.frame, n - 1)] for t in task.transitions], dtype=float)
    crit = np.array([t.critical for t in task.transitions], dtype=bool)
    if len(xs) and (~crit).any():
        ax.vlines(xs[~crit], 0, 3, colors="0.3", linewidths=0.5)
    if crit.any():
        ax.vlines(xs[crit], 0, 3, colors="red", linewidths=1.5)


def _state_labels(ax: Any, task: TaskModel, x: FloatArray) -> None:
    """Write the state letters along the top: all of them, or the ``MAX_LABELS`` widest."""
    states = list(task.states)
    if len(states) > MAX_LABELS:
        width = [x[s.frames[1] + 1] - x[s.frames[0]] for s in states]
        keep = sorted(np.argsort(width, kind="stable")[::-1][:MAX_LABELS])
        states = [states[i] for i in keep]
    for s in states:
        xm = 0.5 * (x[s.frames[0]] + x[s.frames[1] + 1])
        ax.text(xm, 3.05, s.id, ha="center", va="bottom", fontsize=8)
