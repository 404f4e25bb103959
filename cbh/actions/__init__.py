"""What each command does, in library terms: cli -> actions -> {live, outputs, pipeline, sim} -> geometry."""
