"""What each command does, in library terms: cli -> actions -> {live, outputs, pipeline, sim} -> geometry.

One module per command; each takes paths, names and numbers (never ``--flags``) and returns
what the command prints from:

- :mod:`.run`: :func:`~cbh.actions.run.build_run` wires station, sources, pipeline and sinks
  into a :class:`~cbh.live.service.Service` (``cbh run``); also the shared sink helpers.
- :mod:`.replay`: a recording back into Rerun, or reprocessed by the same service loop over
  :class:`~cbh.outputs.record.RecordingSource` (``cbh replay [--reprocess]``).
- :mod:`.pair`: one image pair → :class:`~cbh.result.PairResult` (``cbh pair``).
- :mod:`.triangulate`: pixel pairs → heights and the paper's metrics (``cbh triangulate``).
- :mod:`.simulate`: a synthetic sky sequence with truth to a folder (``cbh simulate``).
- :mod:`.mask`: a camera's static obstacle mask from its frames (``cbh mask``).
- :mod:`.export`, :mod:`.inspect`: tables and descriptions of recordings.
"""
