"""Types in one room: the frozen values the replay passes between its stages and to its sinks."""
