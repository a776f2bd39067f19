"""Reports of a recognised task: the Fig. 25-style text table and the DOF plot.

:func:`render_table` is pure text; :func:`plot_dof` imports matplotlib (Agg backend) only
when called.
"""

from __future__ import annotations

from apo.report.plot import plot_dof
from apo.report.table import render_table, subskill_label

__all__ = ["plot_dof", "render_table", "subskill_label"]
