"""The replay graph: source → sync → detect → solve → fuse → correct → sinks.

Each stage lives in its own module and hands the next one typed, immutable values;
:mod:`agvviz.runner` only assembles the graph from the settings.
"""
