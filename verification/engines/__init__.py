"""Engines behind the seam (``protocol``): the built-in one, and where others join it.

``engine_for(model)`` names the engine that offers a model, ``spec_of(model)`` what the harness may know
of it (its ``ModelSpec``); ``ENGINES`` lists them by name.
"""

from __future__ import annotations

from collections.abc import Mapping

from realtime.errors import InputError, did_you_mean
from realtime.models import ModelSpec

from .builtin import BUILTIN
from .protocol import foreign_spec

#: Every engine the harness can run, by name.
ENGINES = {BUILTIN.name: BUILTIN}


def offered() -> tuple[str, ...]:
    """Every model some engine offers: the built-in ones, then the plug-ins' in the order they came."""
    return tuple(m for e in ENGINES.values() for m in e.models)


def plug_in(model: str) -> bool:
    """Whether ``model`` is a plug-in engine's (not the built-in engine's)."""
    return model not in BUILTIN.models


def spec_of(model: str) -> ModelSpec:
    """What the harness may know of ``model`` (quasi-static or time-stepping, linear, what it represents,
    its costs), as its engine says it (``Engine.models`` maps each name to its ModelSpec). A plug-in that
    lists its models by name only says nothing of them: a time-stepping model, non-linear, whose
    represented terms are unknown."""
    engine = engine_for(model)
    if isinstance(engine.models, Mapping):
        return engine.models[model]
    return foreign_spec(model, f"{engine.name}'s own")


def engine_for(model: str):
    """The engine that offers ``model``; InputError naming the models there are."""
    for engine in ENGINES.values():
        if model in engine.models:
            return engine
    offered = sorted(m for e in ENGINES.values() for m in e.models)
    hint = did_you_mean(model, offered)
    raise InputError(f"model: no engine offers {model!r}{hint}; the models are {', '.join(offered)}")


def load_engine(spec: str):
    """The engine named by ``spec`` (an adapter's name, "newton" or "mujoco": ``adapters.ADAPTERS``; or
    "package.module:Class", or "path/to/file.py:Class"), made and registered in ENGINES for this
    process; InputError naming the spec and what is wrong (the adapters' venv is not built, the module
    does not import, has no such class, or the class is no engine: a name, its models and build)."""
    import importlib
    import importlib.util
    from pathlib import Path

    from .adapters import ADAPTERS, adapter

    if spec in ADAPTERS:
        engine = adapter(spec)
        ENGINES[engine.name] = engine
        return engine
    where, _, name = spec.rpartition(":")
    if not where or not name:
        hint = did_you_mean(spec, ADAPTERS)
        raise InputError(f"--engine {spec!r}{hint}: give {' or '.join(ADAPTERS)}, MODULE:CLASS or FILE.py:CLASS")
    try:
        if where.endswith(".py"):
            loader = importlib.util.spec_from_file_location(Path(where).stem, where)
            if loader is None or not Path(where).is_file():
                raise ImportError(f"no file {where}")
            module = importlib.util.module_from_spec(loader)
            loader.loader.exec_module(module)
        else:
            module = importlib.import_module(where)
    except Exception as exc:  # the user's module: any error in it is its own, named here in one line
        raise InputError(f"--engine {spec}: cannot import {where}: {type(exc).__name__}: {exc}") from None
    cls = getattr(module, name, None)
    if cls is None:
        raise InputError(f"--engine {spec}: {where} has no {name}")
    try:
        engine = cls()
    except Exception as exc:
        raise InputError(f"--engine {spec}: {name}() failed: {type(exc).__name__}: {exc}") from None
    missing = [a for a in ("name", "models", "build") if not hasattr(engine, a)]
    if missing:
        raise InputError(
            f"--engine {spec}: {name} is not an engine: it has no {', '.join(missing)} (docs/contributing.md)"
        )
    taken = {m for e in ENGINES.values() if e.name != engine.name for m in e.models} & set(engine.models)
    if taken:
        raise InputError(f"--engine {spec}: model {sorted(taken)[0]!r} is another engine's already")
    try:
        engine.spec = spec  # how to name it again (the advisor's command that re-runs its pick)
    except AttributeError:
        pass
    ENGINES[engine.name] = engine
    return engine
