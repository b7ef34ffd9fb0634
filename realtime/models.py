"""The registry of real-time models: a name -> a builder of an immutable ``Model``.

Every builder takes plain arrays (points (N, 3) float64 m; tets (M, 4) int, positively oriented), a
``Material`` and a ``Loading`` and returns a ``Model`` whose force kernel the integrators run.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .material import Material
from .model import Loading, Model, lumped_masses, prepare_mesh
from .tensor_mass import TensorMass, linear_tm_energy, linear_tm_force


def build_linear_tm(points, tets, material: Material, loading: Loading | None = None) -> Model:
    """Linear tensor-mass (Cotin et al. 2000), isotropic or transversely isotropic.

    f = -K u with K the P1 linear stiffness; the law ``material.law`` is ignored (always linear).
    """
    points, tets = prepare_mesh(points, tets)
    tm = TensorMass(points, tets, material)
    return Model(
        name="linear-tm",
        points=points,
        tets=tets,
        material=material,
        mass=lumped_masses(points, tets, material.density),
        loading=loading if loading is not None else Loading.free_body(len(points)),
        force_kernel=linear_tm_force,
        energy_kernel=linear_tm_energy,
        data=tm.kernel_data(),
        linear=True,
        extra={"tensors": tm},
    )


MODELS: dict[str, Callable[..., Model]] = {
    "linear-tm": build_linear_tm,
}


def build_model(name: str, points, tets, material: Material, loading: Loading | None = None, **options) -> Model:
    """Build the model registered under ``name``."""
    try:
        builder = MODELS[name]
    except KeyError:
        raise ValueError(f"model = {name!r}: must be one of {', '.join(MODELS)}") from None
    return builder(np.asarray(points), np.asarray(tets), material, loading, **options)
