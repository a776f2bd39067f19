"""Figures for papers (matplotlib, Agg): DOF timeline, state graph, one picture per state.

Everything is drawn from the ``task.json`` document (``docs/task-json.md``) and, for the
state pictures, the two models. Each figure is written as SVG and PNG, readable in print:
lengths carry their unit, DOF axes their kind, every state its letter.
See ``docs/report.md``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from apo.geometry import Polyhedron
    from apo.outputs import OutputSet

__all__ = [
    "FIGURE_FORMATS",
    "direction_text",
    "state_graph_figure",
    "state_picture",
    "subskill_text",
    "timeline_figure",
    "write_figures",
]

FIGURE_FORMATS = ("svg", "png")
KINDS = ("M", "D", "C", "SM", "SD", "SC")
KIND_COLORS = {
    "M": "#4c9be8",
    "D": "#f2a541",
    "C": "#d9534f",
    "SM": "#a6cdf5",
    "SD": "#f9d29d",
    "SC": "#eea6a4",
}
_KIND_NAMES = {
    "M": "maintaining",
    "D": "detaching",
    "C": "constraining",
    "SM": "singular maintaining",
    "SD": "singular detaching",
    "SC": "singular constraining",
}
PALETTE = (
    "#1f77b4",
    "#ff7f0e",
    "#2ca02c",
    "#9467bd",
    "#8c564b",
    "#e377c2",
    "#17becf",
    "#bcbd22",
    "#d62728",
    "#7f7f7f",
)
FREE_COLOR = "#8fa3b8"
CRITICAL = "#c62828"


def state_colors(states: Sequence[Mapping[str, Any]]) -> list[str]:
    """One colour per contact state (as in the HTML report): ``same_as`` shares it."""
    by_id: dict[str, str] = {}
    out: list[str] = []
    k = 0
    for s in states:
        c = by_id.get(str(s.get("same_as"))) if s.get("same_as") else None
        if c is None:
            if s["elements"]:
                c = PALETTE[k % len(PALETTE)]
                k += 1
            else:
                c = FREE_COLOR
        by_id[str(s["id"])] = c
        out.append(c)
    return out


def direction_text(d: Sequence[float]) -> str:
    """``"+x"``, ``"-y"`` for an axis direction, else ``"(0.71, -0.71, 0.00)"``; ``""`` if zero."""
    v = np.asarray(d, dtype=float)
    n = float(np.linalg.norm(v))
    if not n > 0:
        return ""
    v = v / n
    a = int(np.argmax(np.abs(v)))
    if abs(v[a]) > 0.995:
        return ("+" if v[a] > 0 else "\u2212") + "xyz"[a]
    return "(" + ", ".join(f"{x:.2f}" for x in v) + ")"


def subskill_text(k: Mapping[str, Any]) -> str:
    """``"push-to T along -y"``, ``"push-to R(I) about +x"``, ``"slide T"``."""
    name = {"push_to": "push-to", "release": "release", "slide": "slide"}.get(k["kind"], k["kind"])
    sp = "T" if k["space"] == "translation" else "R"
    ty = f"({k['type']})" if k.get("type") else ""
    d = direction_text(k.get("direction") or (0, 0, 0))
    if d:
        d = (" along " if k["space"] == "translation" else " about ") + d
    return f"{name} {sp}{ty}{d}"


def eight_text(s: Mapping[str, Any]) -> str:
    """Return the eight numbers of a state, as the paper's Fig. 25 prints them."""
    f = s["fig25"]
    S = "S " if s["singular"] else ""
    return f"T {S}{f[0]} {f[1]} {f[2]}  R {S}{f[3]} {f[4]} {f[5]}  r {f[6]} {f[7]}"


def _new_figure(w: float, h: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h))
    FigureCanvasAgg(fig)
    return fig


def _spans(states: Sequence[Mapping[str, Any]]) -> list[tuple[float, float]]:
    """Time span of each state: from its first frame to the next state's first frame."""
    out = []
    for i, s in enumerate(states):
        a = float(s["times"][0])
        if i + 1 < len(states):
            b = float(states[i + 1]["times"][0])
        else:
            n = s["frames"][1] - s["frames"][0]
            step = (float(s["times"][1]) - a) / n if n > 0 else 0.0
            b = float(s["times"][1]) + (step if step > 0 else 0.02 * _duration(states))
        out.append((a, b))
    return out


def _duration(states: Sequence[Mapping[str, Any]]) -> float:
    """Duration of the demonstration (s), 1 when it has none."""
    d = float(states[-1]["times"][1]) - float(states[0]["times"][0])
    return d if d > 0 else 1.0


def timeline_figure(task: Mapping[str, Any]) -> Figure:
    """Draw the DOF timeline: stacked M, D, C, SM, SD, SC per state, restraining, letters."""
    states = task["states"]
    spans = _spans(states)
    colors = state_colors(states)
    fig = _new_figure(10.0, 5.2)
    axes = fig.subplots(2, 1, sharex=True)
    for r, (ax, space) in enumerate(zip(axes, ("translation", "rotation"), strict=True)):
        base = np.zeros(len(states))
        left = np.array([a for a, _ in spans])
        width = np.array([b - a for a, b in spans])
        for j, k in enumerate(KINDS):
            h = np.array([s["six"][space][j] for s in states], dtype=float)
            ax.bar(
                left,
                h,
                width=width,
                bottom=base,
                align="edge",
                color=KIND_COLORS[k],
                edgecolor="white",
                linewidth=0.4,
                label=f"{k} ({_KIND_NAMES[k]})",
            )
            base += h
        xs = np.array(spans).ravel()
        ys = np.repeat([s["fig25"][6 + r] for s in states], 2)
        ax.plot(xs, ys, color="black", lw=1.6, ls=":", label="restraining")
        ax.set_ylim(0, 3.05)
        ax.set_yticks([0, 1, 2, 3])
        ax.set_ylabel(f"{space} DOF")
        for t in task["transitions"]:
            x = float(states[[s["id"] for s in states].index(t["to"])]["times"][0])
            if t["critical"]:
                ax.axvline(x, color=CRITICAL, lw=2.2)
            elif not t["direct"]:
                ax.axvline(x, color="#ef6c00", lw=1.2, ls="--")
    total = spans[-1][1] - spans[0][0]
    for s, (a, b), c in zip(states, spans, colors, strict=True):
        if len(states) <= 40 or (b - a) > total / 80:
            axes[0].text(
                0.5 * (a + b),
                3.12,
                s["id"],
                ha="center",
                va="bottom",
                fontsize=10,
                color=c,
                fontweight="bold",
            )
    for t in task["transitions"]:
        if t["critical"]:
            x = float(states[[s["id"] for s in states].index(t["to"])]["times"][0])
            axes[1].text(x, -0.55, "critical", color=CRITICAL, ha="center", va="top", fontsize=8)
    axes[1].set_xlabel("time [s]")
    axes[0].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    fig.suptitle(f"DOF indices per state: {task.get('source') or 'demonstration'}", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    return fig


_DX = 3.9


def _graph_layout(n: int, cols: int) -> list[tuple[float, float]]:
    out = []
    for i in range(n):
        r, c = divmod(i, cols)
        if r % 2:
            c = cols - 1 - c
        out.append((c * _DX, -r * 3.0))
    return out


def state_graph_figure(task: Mapping[str, Any], *, max_rejected: int = 12) -> Figure:
    """Draw the state graph of the paper's Fig. 24/25 (boxes, labelled arrows, rejected runs)."""
    states = task["states"]
    n = len(states)
    cols = max(1, min(n, 5))
    rows = (n + cols - 1) // cols
    pos = _graph_layout(n, cols)
    fig = _new_figure(2.6 * cols + 0.6, 2.1 * rows + 0.8)
    ax = fig.add_axes((0.01, 0.01, 0.98, 0.9))
    index = {s["id"]: i for i, s in enumerate(states)}
    for s, xy, c in zip(states, pos, state_colors(states), strict=True):
        _draw_state_box(ax, s, xy, c)
    for k, t in enumerate(task["transitions"]):
        _draw_transition(ax, k, t, pos[index[t["from"]]], pos[index[t["to"]]])
    _draw_rejected(ax, task, pos, max_rejected)
    ax.set_xlim(-_BOX_W, (cols - 1) * _DX + _BOX_W)
    ax.set_ylim(-(rows - 1) * 3.0 - 2.0, _BOX_H)
    ax.set_aspect("equal")
    ax.axis("off")
    fig.suptitle(
        "State graph (paper Fig. 24/25): T/R = translation/rotation M D C "
        "(S: singular), r = restraining T R",
        fontsize=9,
    )
    return fig


#: Width and height of a state's box in the state graph (data units).
_BOX_W, _BOX_H = 2.3, 1.1


def _draw_state_box(ax: Any, s: Mapping[str, Any], xy: tuple[float, float], color: str) -> None:
    """Draw a state's box: its id (singular: dotted; ``= X`` if the same as X), Fig. 25 numbers."""
    from matplotlib.patches import Rectangle

    x, y = xy
    W, H = _BOX_W, _BOX_H
    ax.add_patch(
        Rectangle((x - W / 2, y - H / 2), W, H, facecolor=color, edgecolor="black",
                  linestyle=":" if s["singular"] else "-", lw=1.2)
    )  # fmt: skip
    head = (
        s["id"]
        + (" (singular)" if s["singular"] else "")
        + (f" = {s['same_as']}" if s.get("same_as") else "")
    )
    ax.text(x, y + 0.2, head, ha="center", va="center", fontsize=10, color="white",
            fontweight="bold")  # fmt: skip
    f, S = s["fig25"], "S " if s["singular"] else ""
    numbers = f"T {S}{f[0]} {f[1]} {f[2]}  R {S}{f[3]} {f[4]} {f[5]}\nr {f[6]} {f[7]}"
    ax.text(x, y - 0.2, numbers, ha="center", va="center", fontsize=7, color="white",
            family="monospace", linespacing=1.1)  # fmt: skip


def _draw_transition(
    ax: Any, k: int, t: Mapping[str, Any], a: tuple[float, float], b: tuple[float, float]
) -> None:
    """Transition ``k`` from the box at ``a`` to the box at ``b``: arrow and sub-skill label."""
    from matplotlib.patches import FancyArrowPatch

    W, H = _BOX_W, _BOX_H
    (ax0, ay0), (bx, by) = a, b
    horiz = abs(ay0 - by) < 1e-9
    sgn = np.sign(bx - ax0) if horiz else 0.0
    start = (ax0 + sgn * W / 2, ay0) if horiz else (ax0, ay0 - H / 2)
    end = (bx - sgn * W / 2, by) if horiz else (bx, by + H / 2)
    col = CRITICAL if t["critical"] else ("#333333" if t["direct"] else "#ef6c00")
    ax.add_patch(
        FancyArrowPatch(start, end, arrowstyle="-|>", mutation_scale=14, color=col,
                        lw=2.6 if t["critical"] else 1.3)
    )  # fmt: skip
    lines = [subskill_text(u).replace(" (", "\n(") for u in t["subskills"]]
    lines = lines or ["(no sub-skill)"]
    if t["critical"]:
        lines.insert(0, "CRITICAL")
    if not t["direct"]:
        lines.insert(0, "not direct")
    mx, my = 0.5 * (start[0] + end[0]), 0.5 * (start[1] + end[1])
    ax.text(
        mx if horiz else mx + 0.12,
        my + 0.1 if horiz else my,
        f"({k + 1}) " + "\n".join(lines),
        ha="center" if horiz else "left",
        va="bottom" if horiz else "center",
        fontsize=6.5,
        color=col,
        linespacing=1.15,
    )


def _draw_rejected(
    ax: Axes, task: Mapping[str, Any], pos: Sequence[tuple[float, float]], max_rejected: int
) -> None:
    from matplotlib.patches import Rectangle

    index = {s["id"]: i for i, s in enumerate(task["states"])}
    rej = sorted(task["rejected"], key=lambda r: r["frames"][0] - r["frames"][1])[:max_rejected]
    slots: dict[int, int] = {}
    placed = 0
    for rj in rej:
        to = index.get(rj["replaced_by"][0], 0) if rj["replaced_by"] else 0
        slot = slots[to] = slots.get(to, 0) + 1
        if slot > 2:
            continue
        placed += 1
        bx, by = pos[to]
        x, y, w, h = bx + (slot - 1) * 1.7 - 0.85, by - 1.4, 1.6, 0.62
        ax.add_patch(
            Rectangle(
                (x - w / 2, y - h / 2), w, h, facecolor="#eceff1", edgecolor="#9e9e9e", ls=":"
            )
        )
        ax.plot([x - w / 2, x + w / 2], [y - h / 2, y + h / 2], color=CRITICAL, lw=1.2)
        ax.plot([x - w / 2, x + w / 2], [y + h / 2, y - h / 2], color=CRITICAL, lw=1.2)
        ax.plot([x, bx], [y + h / 2, by - 0.5], color="#9e9e9e", lw=0.8, ls=":")
        reason = rj["reason"] if len(rj["reason"]) <= 60 else rj["reason"][:59] + "\u2026"
        import textwrap

        ax.text(
            x,
            y,
            f"frames {rj['frames'][0]}\u2013{rj['frames'][1]}\n"
            + "\n".join(textwrap.wrap(reason, 26)[:2]),
            ha="center",
            va="center",
            fontsize=5.5,
            color="#222222",
            bbox={"facecolor": "white", "alpha": 0.6, "lw": 0, "pad": 0.5},
        )
    if len(task["rejected"]) > placed:
        ax.text(
            1.0,
            0.0,
            f"{len(task['rejected']) - placed} more rejected run(s) in task.json",
            transform=ax.transAxes,
            ha="right",
            va="bottom",
            fontsize=7,
            color="#555555",
        )


def _posed_triangles(poly: Polyhedron, X: np.ndarray | None, scale: float) -> np.ndarray:
    V = np.asarray(poly.vertices, dtype=float)
    if X is not None:
        V = V @ X[:3, :3].T + X[:3, 3]
    T = np.concatenate([np.asarray(t).reshape(-1, 3) for t in poly.face_triangles])
    return np.asarray(V[T] * scale, dtype=np.float64)


def _edge_lines(poly: Polyhedron, X: np.ndarray | None, scale: float) -> Any:
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    V = np.asarray(poly.vertices, dtype=float)
    if X is not None:
        V = V @ X[:3, :3].T + X[:3, 3]
    return Line3DCollection(V[np.asarray(poly.edges)] * scale, colors="#333333", linewidths=0.6)


def state_picture(
    task: Mapping[str, Any],
    k: int,
    grasped: Polyhedron | None,
    environment: Polyhedron | None,
) -> Figure:
    """Draw the two objects at state ``k``'s pose, its contact points and separating normals.

    Two views: the whole scene, and a close-up of the contacts (the scene again when the
    state has none).
    """
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from apo.spatial import pose_from_position_quaternion
    from apo.task import UNITS

    s = task["states"][k]
    units = str(task["units"])
    scale = 1.0 / UNITS[units]
    X = pose_from_position_quaternion(
        np.asarray(s["pose"]["position"], dtype=float) / scale, np.asarray(s["pose"]["quaternion"])
    )
    color = state_colors(task["states"])[k]
    fig = _new_figure(10.0, 4.8)
    pts = np.array([e["point"] for e in s["elements"]]).reshape(-1, 3)
    tris = []
    if environment is not None:
        tris.append((_posed_triangles(environment, None, scale), "#b0b7c0", 0.25, "environment"))
    if grasped is not None:
        tris.append((_posed_triangles(grasped, X, scale), color, 0.85, "grasped"))
    allv = np.concatenate([t[0].reshape(-1, 3) for t in tris] + [pts]) if tris or len(pts) else None
    ref = min((p.scale for p in (grasped, environment) if p is not None), default=0.0) * scale
    ref = ref or 20 * float(task["threshold"])
    for j in range(2):
        ax = fig.add_subplot(1, 2, j + 1, projection="3d")
        for tri, c, alpha, name in tris:
            coll = Poly3DCollection(tri, facecolor=c, edgecolor="none", alpha=alpha, label=name)
            ax.add_collection3d(coll)
        for poly, Xp in ((environment, None), (grasped, X)):
            if poly is not None:
                ax.add_collection3d(_edge_lines(poly, Xp, scale))
        _draw_contacts(ax, s["elements"], 0.15 * ref)
        if j == 0 and allv is not None and len(allv):
            lo, hi = allv.min(axis=0), allv.max(axis=0)
        elif len(pts):
            c0 = pts.mean(axis=0)
            r = max(0.35 * ref, float(np.ptp(pts, axis=0).max()) * 0.75)
            lo, hi = c0 - r, c0 + r
        elif allv is not None:
            lo, hi = allv.min(axis=0), allv.max(axis=0)
        else:
            lo, hi = -np.ones(3), np.ones(3)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(tuple(np.maximum(hi - lo, 1e-9)))
        for axis, name in zip((ax.set_xlabel, ax.set_ylabel, ax.set_zlabel), "xyz", strict=True):
            axis(f"{name} [{units}]", fontsize=8)
        ax.tick_params(labelsize=6)
        ax.view_init(elev=24, azim=-58)
        ax.set_title("scene" if j == 0 else "contacts (close-up)", fontsize=9)
        if j == 0:
            ax.legend(loc="upper left", fontsize=7, frameon=False)
    sing = " (singular)" if s["singular"] else ""
    fig.suptitle(
        f"State {s['id']}{sing}, frames {s['frames'][0]}\u2013{s['frames'][1]}: {eight_text(s)}; "
        f"{len(s['elements'])} contact element(s)",
        fontsize=10,
    )
    return fig


def _draw_contacts(ax: Any, elements: Sequence[Mapping[str, Any]], length: float) -> None:
    reg = [e for e in elements if len(e["normals"]) <= 1]
    sing = [e for e in elements if len(e["normals"]) > 1]
    for group, style, name in (
        (reg, {"c": "black", "marker": "o", "s": 14}, "contact point"),
        (sing, {"c": "#d81b60", "marker": "D", "s": 30}, "singular element"),
    ):
        if not group:
            continue
        P = np.array([e["point"] for e in group])
        ax.scatter(P[:, 0], P[:, 1], P[:, 2], depthshade=False, label=name, **style)
    rows = [(e["point"], n) for e in elements for n in e["normals"]]
    if rows:
        P = np.array([r[0] for r in rows])
        N = np.array([r[1] for r in rows]) * length
        ax.quiver(
            P[:, 0],
            P[:, 1],
            P[:, 2],
            N[:, 0],
            N[:, 1],
            N[:, 2],
            color="#2e7d32",
            lw=1.2,
            arrow_length_ratio=0.3,
            label="separating normal",
        )


def write_figures(
    task: Mapping[str, Any],
    out_dir: str | Path | OutputSet,
    *,
    grasped: Polyhedron | None = None,
    environment: Polyhedron | None = None,
    formats: Sequence[str] = FIGURE_FORMATS,
    dpi: int = 200,
) -> list[Path]:
    """Write every figure of ``task`` to ``out_dir`` in ``formats``; return the paths.

    Names: ``dof_timeline``, ``state_graph``, ``state_<ID>`` (one per state). ``out_dir``
    may be an open :class:`apo.outputs.OutputSet` (the paths returned are then the final
    ones, where the files appear when the set commits).
    """
    from apo.outputs import OutputSet

    if isinstance(out_dir, OutputSet):
        outs = out_dir

        def target(name: str) -> tuple[Path, Path]:
            return outs.path(name), outs.final(name)
    else:
        folder = Path(out_dir)
        folder.mkdir(parents=True, exist_ok=True)

        def target(name: str) -> tuple[Path, Path]:
            return folder / name, folder / name

    figs: list[tuple[str, Any]] = [
        ("dof_timeline", lambda: timeline_figure(task)),
        ("state_graph", lambda: state_graph_figure(task)),
    ]
    for k, s in enumerate(task["states"]):
        figs.append((f"state_{s['id']}", lambda k=k: state_picture(task, k, grasped, environment)))
    from matplotlib import rc_context

    written = []
    # text stays text in SVG (searchable, editable for a paper)
    with rc_context({"svg.fonttype": "none"}):
        for name, make in figs:
            fig = make()
            for fmt in formats:
                path, final = target(f"{name}.{fmt}")
                fig.savefig(path, format=fmt, dpi=dpi, bbox_inches="tight")
                written.append(final)
    return written
