"""The real-time models, one file each: a name -> its ``ModelSpec`` (``spec.py``) and builder.

Every module of this folder that defines ``SPEC`` is a model: adding one is adding its file (and its
kernel if it is new, and its test); nothing else names it. Every builder takes plain arrays (points
(N, 3) float64 m; tets (M, 4) int, positively oriented), a ``Material`` and a ``Loading`` and returns a
``Model`` whose force kernel the integrators run.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from collections.abc import Callable

import numpy as np

from ..errors import InputError
from ..material import Material, Materials
from ..model import PRECISIONS, Loading, Model
from .base import ModelSpec


def _discover() -> dict[str, ModelSpec]:
    """Every module here with a SPEC, by its name, in their ``rank`` order (then by name)."""
    found = []
    for info in pkgutil.iter_modules(__path__):
        spec = getattr(importlib.import_module(f"{__name__}.{info.name}"), "SPEC", None)
        if isinstance(spec, ModelSpec):
            found.append(spec)
    names = [s.name for s in found]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise RuntimeError(f"realtime.models: two files define the model {twice[0]!r}")
    return {s.name: s for s in sorted(found, key=lambda s: (s.rank, s.name))}


#: Every model's spec, by name, in listing order.
SPECS: dict[str, ModelSpec] = _discover()
#: Every model's builder, by name.
MODELS: dict[str, Callable[..., Model]] = {name: s.build for name, s in SPECS.items()}


def spec(name: str) -> ModelSpec:
    """The spec of model ``name``; InputError naming the models there are."""
    try:
        return SPECS[name]
    except KeyError:
        raise InputError(f"model = {name!r}: must be one of {', '.join(SPECS)}") from None


def unrepresented(name: str, material: Material | Materials) -> list[str]:
    """What ``material`` asks of model ``name`` that it does not represent (``ModelSpec.unrepresented``)."""
    return spec(name).unrepresented(material)


def build_model(
    name: str, points, tets, material: Material | Materials, loading: Loading | None = None, **options
) -> Model:
    """Build the model registered under ``name``. ``options`` go to its builder; ``precision``
    ("float64", the default, or "float32" for a model whose spec says ``float32``) is checked here for
    every model."""
    model = spec(name)
    precision = options.pop("precision", "float64")
    if precision not in PRECISIONS:
        raise InputError(f"precision = {precision!r}: must be one of {', '.join(PRECISIONS)}")
    if precision != "float64":
        if not model.float32:
            single = ", ".join(s.name for s in SPECS.values() if s.float32)
            raise InputError(f"precision = {precision!r}: {name} runs in float64 only ({single} run in float32)")
        options["precision"] = precision
    params = inspect.signature(model.build).parameters
    accepted = [k for k in params if k not in ("points", "tets", "material", "loading")]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise InputError(f"{name}: option {unknown[0]!r} is not one of its options ({', '.join(accepted) or 'none'})")
    return model.build(np.asarray(points), np.asarray(tets), material, loading, **options)


def renumber(points, tets) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh (points (N, 3) m, tets (M, 4) int) numbered along the body, for speed: (points (N, 3)
    float64, tets (M, 4) int64, vertex_order (N,) int64 the old index of each new vertex); a state in
    the old numbering maps to the new one by ``u[vertex_order]``. The same tetrahedra, each with its
    corners in the same order (realtime.geometry.renumbered). Raises InvalidMeshError for a mesh
    build_model would refuse."""
    from ..geometry import renumbered
    from ..model import prepare_mesh

    return renumbered(*prepare_mesh(points, tets))


__all__ = ["MODELS", "SPECS", "ModelSpec", "build_model", "renumber", "spec", "unrepresented"]
