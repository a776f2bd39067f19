"""The paper's Fig. 25 as a text table: states, their eight numbers, and the transitions.

Each state row shows its letter, frames, time span, the eight numbers (translation M D C,
rotation M D C, translation and rotation restraining; singular M D C in a singular state,
marked ``S``), and its number of contact elements. Between two states a line shows the
transition number, its sub-skills and ``CRITICAL`` when it is a critical transition.
"""

from __future__ import annotations

from apo.task import SubSkill, TaskModel

__all__ = ["render_table", "subskill_label"]

_KIND = {"push_to": "push-to", "release": "release", "slide": "slide"}
_SPACE = {"translation": "T", "rotation": "R"}


def subskill_label(s: SubSkill) -> str:
    """Return a short label such as ``"push-to T"`` or ``"push-to R(I)"``."""
    label = f"{_KIND.get(s.kind, s.kind)} {_SPACE.get(s.space, s.space)}"
    return f"{label}({s.type})" if s.type else label


MAX_REJECTED_LINES = 12
"""Rejected runs listed in the table at most (all are in ``task.json``)."""


def render_table(task: TaskModel, *, units: str | None = None) -> str:
    """Return the Fig. 25-style table of ``task`` as text (no trailing newline).

    Parameters
    ----------
    task : TaskModel
    units : str, optional
        Ignored placeholder for symmetry with the JSON writer; times are in seconds.

    Returns
    -------
    str
        One row per state and one line per transition, e.g.::

            state  frames     time [s]        T: M D C  R: M D C  rT rR  elements
            A      0-3        0.000-0.300        3 0 0     3 0 0   0  0  0
              (1) A->B  push-to T, push-to R(I)
            B      4-12       ...
    """
    del units
    head = (
        f"{'state':<6} {'frames':<11} {'time [s]':<15} {'T: M D C':>9} {'R: M D C':>9} "
        f"{'rT':>3} {'rR':>2}  elements"
    )
    lines = [head, "-" * len(head)]
    for i, s in enumerate(task.states):
        f = s.fig25
        sid = s.id + ("*" if s.singular else "")
        frames = f"{s.frames[0]}-{s.frames[1]}"
        times = f"{s.times[0]:.3f}-{s.times[1]:.3f}"
        t = f"{'S ' if s.singular else ''}{f[0]} {f[1]} {f[2]}"
        r = f"{'S ' if s.singular else ''}{f[3]} {f[4]} {f[5]}"
        note = [] if s.pose_converged else ["pose not corrected"]
        if s.same_as:
            note.append(f"= {s.same_as}")
        extra = f"  ({', '.join(note)})" if note else ""
        lines.append(
            f"{sid:<6} {frames:<11} {times:<15} {t:>9} {r:>9} {f[6]:>3} {f[7]:>2}  "
            f"{len(s.elements)}{extra}"
        )
        if i < len(task.transitions):
            tr = task.transitions[i]
            skills = ", ".join(subskill_label(k) for k in tr.subskills) or "-"
            mark = "  CRITICAL" if tr.critical else ""
            bad = "  (not a direct transition)" if not tr.direct else ""
            lines.append(f"  ({i + 1}) {tr.from_id}->{tr.to_id}{mark}  {skills}{bad}")
    lines.append("* singular state: the numbers are singular M D C;  rT rR: restraining DOF")
    if task.rejected:
        lines.append(f"repair: {len(task.rejected)} observed run(s) rejected")
        # the longest runs first (a long run replaced tells more than a 1-frame blip)
        shown = sorted(task.rejected, key=lambda r: r.frames[0] - r.frames[1])
        shown = sorted(shown[:MAX_REJECTED_LINES], key=lambda r: r.frames[0])
        for rj in shown:
            span = f"{rj.frames[0]}-{rj.frames[1]}"
            lines.append(f"  frames {span} -> {','.join(rj.replaced_by)}: {rj.reason}")
        if len(task.rejected) > len(shown):
            lines.append(
                f'  ... and {len(task.rejected) - len(shown)} shorter run(s): see "rejected" '
                "in task.json"
            )
    return "\n".join(lines)
