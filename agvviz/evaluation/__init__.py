"""Errors against truth and run statistics. Numpy only."""

from agvviz.evaluation.summary import FrameScore, summarize

__all__ = ["FrameScore", "summarize"]
