"""Errors against truth and run statistics. Numpy and scipy only (no rerun, no files).

- :mod:`~agvviz.evaluation.summary`: the per-run summary stored in every ``.rrd``, and timing.
- :mod:`~agvviz.evaluation.trajectory`: alignment (SE(3), SE(2), yaw), APE, RPE, time offset.
- :mod:`~agvviz.evaluation.statistics`: statistics, block-bootstrap intervals, Wilcoxon.
- :mod:`~agvviz.evaluation.comparison`: per-run metrics and the paired comparison of two runs.
- :mod:`~agvviz.evaluation.expression`: the safe ``--fail-if`` grammar.
- :mod:`~agvviz.evaluation.gates`: the metrics ``run``/``diff --fail-if`` read (suspect counts
  too) and each condition's verdict; :mod:`~agvviz.evaluation.junit`: the verdicts as JUnit XML.
- :mod:`~agvviz.evaluation.suspect_report`: suspect frames and stretches in words (the suspects
  log line, the summary rows, the terminal's stretch table).
"""

from agvviz.evaluation.summary import FrameScore, summarize, timing

__all__ = ["FrameScore", "summarize", "timing"]
