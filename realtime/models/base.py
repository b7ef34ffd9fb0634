"""What the models share: their ``ModelSpec`` (what the rest of the project may know of a model, one per
file of this folder) and the parts their builders assemble a Model from (the rest stiffness and
eigenvalue bound of the tetrahedral models, a quasi-static model made from a time-stepping one).

A study, a benchmark or the advisor reads a model's facts (through the engine seam,
``verification.engines``), never a table of model names of its own: a model's name, builder, law and
costs are said once, in its file. This file holds no model (no ``SPEC``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from ..blocks import BlockData, block_data
from ..errors import InputError, ModelRestriction
from ..geometry import shape_gradients
from ..material import Materials
from ..model import PRECISIONS, Loading, Model, lumped_masses, no_scratch, prepare_mesh
from ..tensor_mass import TensorMass, element_elasticity
from ..threaded import block_kernel, check_threads

#: The material terms beyond E, nu and rho a model may represent: "fibres" (a transversely isotropic
#: law) and "penalty" (Material.volume_penalty, the incompressibility term of Picinbono et al. 2003).
TERMS = ("fibres", "penalty")
#: The integrators of a model that jumps to equilibrium instead of integrating in time.
QUASI_STATIC = ("quasi-static",)


@dataclass(frozen=True)
class ModelSpec:
    """One model's facts.

    Attributes:
        name: the name a scene, a study and the command line use ("stvk-tm").
        build: the builder ``build(points (N, 3) float64 m, tets (M, 4) int, material, loading=None,
            **options) -> Model``; its keyword parameters past ``loading`` are the model's options. None
            for a model another engine runs (it is built behind the seam, not here).
        law: the constitutive law the model discretises, and how (one line, with its source).
        drops: what it gives up against that law solved by P1 finite elements (one line; "" for
            nothing).
        represents: the terms of TERMS it represents; a material asking for another runs without it,
            and every result says so (``unrepresented``). None where the engine did not say (a plug-in
            that lists its models by name): nothing is then said of it.
        integrators: what advances it. A time-stepping model: "symplectic-euler" first, then the
            others the studies try it with ("implicit-euler" where it settles a static scene in tens of
            steps, the advisor's extra candidates). QUASI_STATIC for a model with its own update to
            equilibrium (no time step, no critical step).
        linear: its force is linear in u (the stiffness never changes): its error against the
            non-linear reference is what linear elasticity gives up.
        mechanics: False for a model with no internal force and no energy (a geometric baseline): what a
            force-field test cannot test.
        float32: it builds with precision = "float32" too (``Model.precision``).
        own_law: the truth's law (``realtime.material.LAWS``) the model is that law's P1 solution of,
            Lame constants matched at rest: against the P1 truth of it on the same mesh, its distance is
            its numerics alone. None where no continuum law is its limit (a corotated or switched law,
            springs, a mesh of its own).
        cuttable: it supports cutting and suturing (``realtime.topology``).
        own_mesh: it runs on a mesh of its own made from the scene's (adaptive refinement): its error's
            mesh part is not P1's on the scene's mesh, and no finer scene mesh is proposed for it.
        memory: the bytes its precomputation holds, a function of (dofs, surface dofs); None where that
            is negligible (sparse, in proportion to the mesh).
        cost: its cost class, 0 (cheapest) and up: the heaviest compile first (``realtime.precompile``,
            from 2) and settle first (``verification.studies.prefetch``), so that the last job of a
            pool is a short one.
        work: its force kernel's work per element, counted from the source: {"tet" | "vertex" | "edge":
            (flops, streamed bytes)}; empty where it is not a fixed count (``verification.bench.roofline``).
        rank: where it stands in listings (docs/models.md's order): smaller first.
    """

    name: str
    build: Callable | None
    law: str
    drops: str = ""
    represents: tuple[str, ...] | None = ()
    integrators: tuple[str, ...] = ("symplectic-euler",)
    linear: bool = False
    mechanics: bool = True
    float32: bool = False
    own_law: str | None = None
    cuttable: bool = False
    own_mesh: bool = False
    memory: Callable[[float, float], float] | None = None
    cost: int = 0
    work: dict = field(default_factory=dict)
    rank: int = 1000

    def __post_init__(self):
        unknown = [t for t in self.represents or () if t not in TERMS]
        if unknown:
            raise ValueError(f"model {self.name}: represents {unknown[0]!r}: not one of {', '.join(TERMS)}")
        if not self.integrators:
            raise ValueError(f"model {self.name}: integrators: none given")

    @property
    def quasi_static(self) -> bool:
        """Whether it jumps to equilibrium (its own update) instead of integrating in time."""
        return self.integrators == QUASI_STATIC

    def unrepresented(self, material) -> list[str]:
        """What ``material`` (a Material or Materials) asks of this model that it does not represent:
        one phrase per term with the material's value, e.g. "the volume penalty (volume_penalty = 50000
        Pa)"."""
        mats = getattr(material, "materials", (material,))
        asked = {
            "fibres": next((f"the fibres (young_fiber = {m.young_fiber:g} Pa)" for m in mats if m.transverse), None),
            "penalty": next(
                (
                    f"the volume penalty (volume_penalty = {m.volume_penalty:g} Pa)"
                    for m in mats
                    if m.volume_penalty > 0
                ),
                None,
            ),
        }
        if self.represents is None:
            return []
        return [text for term, text in asked.items() if text is not None and term not in self.represents]


def tet_rest_stiffness(model: Model):
    """The P1 linear stiffness of the model's material, scipy CSR (3N, 3N) N/m: linear-tm's own tensors,
    or what the element models linearise to at rest (the volume penalty left out)."""
    tm = model.extra.get("tensors") or TensorMass(model.points, model.tets, model.material)
    return tm.matrix()


def tet_eigenvalue_bound(model: Model) -> float:
    """max over the tetrahedra of lambda_max(K_e, M_e), 1/s^2: K_e the P1 stiffness of each
    tetrahedron's material's rest linearisation (fibres and the volume penalty included), M_e = rho V / 4
    at each vertex, rho its material's: the stiffest and lightest material sets the bound."""
    mats = model.materials
    rho = mats.per_tet("density")
    grads, vol = shape_gradients(model.points, model.tets)
    lam_max = 0.0
    for start in range(0, len(vol), 4096):  # bounded memory: (4096, 12, 12) at a time
        part = slice(start, start + 4096)
        g, v = grads[part], vol[part]
        C = element_elasticity(model.points, model.tets[part], mats.subset(part), penalty=True)
        ke = np.einsum("maj,mijkl,mbl->maibk", g, C, g).reshape(len(v), 12, 12) * v[:, None, None]
        ev = np.linalg.eigvalsh(ke)[:, -1] / (rho[part] * v / 4.0)
        lam_max = max(lam_max, float(ev.max()))
    return lam_max


def assemble(
    name,
    points,
    tets,
    material,
    loading,
    force,
    energy,
    data,
    linear,
    scratch=no_scratch,
    rest=tet_rest_stiffness,
    bound=tet_eigenvalue_bound,
    precision="float64",
    **extra,
) -> Model:
    """The Model ``name`` of a prepared mesh (points (N, 3) float64 m, tets (M, 4) int64), its material
    (lumped masses from its densities) and loading (a free body when None), with the force and energy
    kernels, their ``data`` and ``scratch`` maker, its rest stiffness and eigenvalue bound (functions of
    the model), ``linear`` (its force linear in u) and ``extra`` (model-specific objects)."""
    if loading is not None:
        loading.check(len(points))
    return Model(
        name=name,
        points=points,
        tets=tets,
        material=material,
        mass=lumped_masses(points, tets, Materials.of(material, len(tets)).per_tet("density")),
        loading=loading if loading is not None else Loading.free_body(len(points)),
        force_kernel=force,
        energy_kernel=energy,
        data=data,
        new_scratch=scratch,
        rest_stiffness_of=rest,
        eigenvalue_bound_of=bound,
        linear=linear,
        extra=extra,
        precision=precision,
    )


def block_model(
    name, points, tets, material, loading, kernels, threads: int, precision: str = "float64", isotropic: str = ""
) -> Model:
    """The Model ``name`` of an element model on blocks of tetrahedra (``realtime.blocks``): ``kernels`` its
    serial (force, energy, scratch maker of a float type); its force on ``threads`` threads
    (``realtime.threaded``) in ``precision`` (Model.precision). ``isotropic``: why the model refuses a
    material with fibres (InputError naming the model), or "" where it takes one."""
    threads = check_threads(threads)
    points, tets = prepare_mesh(points, tets)
    if isotropic and Materials.of(material, len(tets)).transverse:
        raise InputError(f"{name}: isotropic materials only ({isotropic})")
    dtype = PRECISIONS[precision]
    btets, geo, prm = block_data(points, tets, material, dtype)
    data = BlockData(btets, geo, prm, np.ones(len(btets), dtype=np.bool_))
    force, energy, scratch = kernels
    kernel = block_kernel(force, energy, partial(scratch, dtype), data, len(points), threads)
    return assemble(
        name, points, tets, material, loading, *kernel[:3], False, kernel[3], precision=precision, threads=threads
    )


def with_quasistatic(model: Model, name: str, solver) -> Model:
    """``model`` renamed ``name``, with ``solver(model)`` as its quasi-static solver (a class or a function
    of the model returning the solver). It steps no more in time, and its cutting tensors are not its
    own to cut: a cut would leave the solver's factorisation behind. A loading with rigid tools is refused
    (ModelRestriction): its contact has no place in a precomputed or condensed linear solve."""
    contacts = model.loading.contacts
    if contacts is not None and contacts.count:
        raise ModelRestriction(
            f"{name}: the loading has {contacts.count} rigid tool(s) (a [[tool]] in contact); this quasi-static "
            "model prescribes its tools' vertices and has no contact: use a time-stepping model"
        )
    extra = {k: v for k, v in model.extra.items() if k != "cuttable"}
    extra["quasistatic"] = solver(model)
    return Model(**{**model.__dict__, "name": name, "extra": extra})
