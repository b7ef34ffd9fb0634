"""linear-tm: linear tensor-mass (Cotin et al. 2000), isotropic or transversely isotropic; the one
model that cuts and sutures (``realtime.topology``)."""

from __future__ import annotations

import numpy as np

from ..errors import InputError, index_array
from ..material import Material, Materials
from ..model import PRECISIONS, Loading, Model, check_float64, prepare_mesh
from ..tensor_mass import TensorMass
from ..threaded import check_threads, linear_tm_kernel
from .base import ModelSpec, assemble

NAME = "linear-tm"


def build(
    points,
    tets,
    material: Material | Materials,
    loading: Loading | None = None,
    threads: int = 1,
    precision: str = "float64",
) -> Model:
    """Linear tensor-mass (Cotin et al. 2000), isotropic or transversely isotropic.

    f = -K u with K the P1 linear stiffness; the law ``material.law`` is ignored (always linear).
    ``threads`` > 1: the force on that many threads (realtime.threaded). ``precision``: Model.precision.
    """
    threads = check_threads(threads)
    points, tets = prepare_mesh(points, tets)
    tm = TensorMass(points, tets, material)
    force, energy, data, scratch = linear_tm_kernel(tm, threads, PRECISIONS[precision])
    return assemble(
        NAME,
        points,
        tets,
        material,
        loading,
        force,
        energy,
        data,
        True,
        scratch,
        precision=precision,
        tensors=tm,
        generation=tm.generation,
        threads=threads,
        cuttable=True,
    )


def cut(model: Model, which) -> Model:
    """Remove tetrahedra ``which`` from a linear tensor-mass model (Cotin et al. 2000).

    ``which`` indexes the tetrahedra of the mesh the model was built on, so indices stay valid from one
    cut to the next.

    The vertex and edge tensors of the removed tetrahedra's vertices and edges are updated in place,
    and the lumped masses too; a vertex left with no tetrahedron is held fixed. The cost is in
    proportion to the cut, besides copying the masses (N floats): the new model's tetrahedra are made
    when first read (``model.Deferred``). One tetrahedron of liver-x10 (57 837) is measured by make
    bench. Returns the new Model. The old one
    shares the updated tensors but not the new masses and constraints: every integrator refuses to
    step it from then on (InputError), so a thread still holding it fails at once instead of running a
    model that is half the old and half the new.
    """
    tm = model.extra.get("tensors")
    if not model.extra.get("cuttable") or tm is None:
        raise InputError(f"cut: {model.name} does not support cutting ({NAME} does)")
    check_float64(model, "cut")
    which = tm.remove(index_array("cut: which", which, len(tm.tets)))
    touched = tm.tets[which].ravel()
    mass = model.mass.copy()
    mats = tm.materials
    density = np.array([m.density for m in mats.materials])[mats.index[which]]  # per_tet reads all M
    np.subtract.at(mass, touched, np.repeat(density * tm.volumes[which] / 4.0, 4))
    alone = tm.valence[touched] == 0
    orphans = np.unique(touched[alone]) if alone.any() else touched[:0]
    from ..topology import changed_model

    return changed_model(model, tm, model.points, mass, model.loading, data=model.data, orphans=orphans)


SPEC = ModelSpec(
    name=NAME,
    build=build,
    own_law="linear",
    law="linear elasticity (small strain), P1 tetrahedra as vertex and edge tensors (Cotin et al. 2000)",
    drops="the geometric non-linearity: wrong under large rotations and stretches",
    represents=("fibres",),
    integrators=("symplectic-euler", "implicit-euler"),
    linear=True,
    float32=True,
    cuttable=True,
    cost=1,
    # difference form: 8 bytes (row start) a vertex, and 39 flops (3 differences, two 3x3 products) and
    # 80 bytes (tensor, column) an edge
    work={"vertex": (0.0, 8.0), "edge": (39.0, 80.0)},
    rank=0,
)
