"""Runs and their cache: the reference of a scene (``reference``), a model run through the engine
seam (``simulate``), a run against its reference (``compare``), the result files (``results``), the
cached rows (``store``) and the solves and settlings done ahead on every core (``prefetch``)."""
