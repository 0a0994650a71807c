"""The batch-calibration report (``tembayes report``): gather, then render.

- :mod:`tembayes.report.content` -- :func:`build_report` gathers a
  :class:`BatchReport` (numbers, tables, PNG figures) from a run and its batch;
- :mod:`tembayes.report.tolerances` -- the pass/fail checks per module;
- :mod:`tembayes.report.html` -- :func:`write_report` renders one
  self-contained ``report.html`` (and ``report.json``).
"""

from tembayes.report.content import BatchReport, build_report
from tembayes.report.html import render_html, write_report

__all__ = ["BatchReport", "build_report", "render_html", "write_report"]
