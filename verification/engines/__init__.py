"""Engines behind the seam (``protocol``): the built-in one, and where others join it.

``engine_for(model)`` names the engine that offers a model; ``ENGINES`` lists them by name.
"""

from __future__ import annotations

from realtime.errors import InputError

from .builtin import BUILTIN

#: Every engine the harness can run, by name.
ENGINES = {BUILTIN.name: BUILTIN}


def engine_for(model: str):
    """The engine that offers ``model``; InputError naming the models there are."""
    for engine in ENGINES.values():
        if model in engine.models:
            return engine
    offered = sorted(m for e in ENGINES.values() for m in e.models)
    raise InputError(f"model: no engine offers {model!r}; the models are {', '.join(offered)}")
