"""The replay: one graph of stages (sync, detect, solve, fuse, correct, studies) over a recording, feeding sinks."""
