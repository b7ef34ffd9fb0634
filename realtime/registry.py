"""The registry of real-time models: a name -> a builder of an immutable ``Model``.

Every builder takes plain arrays (points (N, 3) float64 m; tets (M, 4) int, positively oriented), a
``Material`` and a ``Loading`` and returns a ``Model`` whose force kernel the integrators run.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from functools import partial

import numpy as np
import scipy.sparse as sp

from .adaptive import build_adaptive_tm
from .blocks import BlockData, block_data, block_scratch
from .corotational import corotational_energy, corotational_force, corotational_scratch
from .errors import InputError, index_array, is_real
from .geometry import renumbered, shape_gradients, signed_volumes, unique_edges
from .hybrid import RELEASE, HybridData, hybrid_energy, hybrid_force, hybrid_scratch
from .material import Material, Materials
from .model import PRECISIONS, Loading, Model, check_float64, lumped_masses, no_scratch, prepare_mesh
from .springs import SpringData, spring_energy, spring_force
from .stvk import stvk_energy, stvk_force
from .tensor_mass import TensorMass, assemble_blocks, element_elasticity
from .threaded import block_kernel, check_threads, linear_tm_kernel


def build_linear_tm(
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
    return _model(
        "linear-tm",
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
    )


def renumber(points, tets) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh (points (N, 3) m, tets (M, 4) int) numbered along the body, for speed: (points (N, 3)
    float64, tets (M, 4) int64, vertex_order (N,) int64 the old index of each new vertex); a state in
    the old numbering maps to the new one by ``u[vertex_order]``. The same tetrahedra, each with its
    corners in the same order (realtime.geometry.renumbered). Raises InvalidMeshError for a mesh
    build_model would refuse."""
    return renumbered(*prepare_mesh(points, tets))


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
    if model.name != "linear-tm" or tm is None:
        raise InputError(f"cut: {model.name} does not support cutting (linear-tm does)")
    check_float64(model, "cut")
    which = tm.remove(index_array("cut: which", which, len(tm.tets)))
    touched = tm.tets[which].ravel()
    mass = model.mass.copy()
    mats = tm.materials
    density = np.array([m.density for m in mats.materials])[mats.index[which]]  # per_tet reads all M
    np.subtract.at(mass, touched, np.repeat(density * tm.volumes[which] / 4.0, 4))
    alone = tm.valence[touched] == 0
    orphans = np.unique(touched[alone]) if alone.any() else touched[:0]
    from .topology import changed_model

    return changed_model(model, tm, model.points, mass, model.loading, data=model.data, orphans=orphans)


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


def spring_rest_stiffness(model: Model):
    """The springs' stiffness at rest, scipy CSR (3N, 3N) N/m: k e e^T on each edge of direction e."""
    X, edges, k = model.points, model.data.edges, model.extra["stiffness"]
    d = X[edges[:, 1]] - X[edges[:, 0]]
    d /= np.linalg.norm(d, axis=1)[:, None]
    b = k[:, None, None] * d[:, :, None] * d[:, None, :]
    i, j = edges[:, 0], edges[:, 1]
    rows = np.concatenate([i, j, i, j])
    cols = np.concatenate([i, j, j, i])
    return assemble_blocks(rows, cols, np.concatenate([b, b, -b, -b]), model.n_vertices)


def spring_eigenvalue_bound(model: Model) -> float:
    """max over the springs of k (1/m_a + 1/m_b), 1/s^2, each vertex's mass shared equally among its
    springs (the element eigenvalue inequality with the springs as elements)."""
    edges, k = model.data.edges, model.data.stiffness
    degree = np.bincount(edges.ravel(), minlength=model.n_vertices)
    share = model.mass / np.maximum(degree, 1)
    return float(np.max(k * (1.0 / share[edges[:, 0]] + 1.0 / share[edges[:, 1]])))


def _model(
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


def build_stvk_tm(
    points,
    tets,
    material: Material | Materials,
    loading: Loading | None = None,
    threads: int = 1,
    precision: str = "float64",
) -> Model:
    """Non-linear StVK tensor-mass (Picinbono et al. 2003), isotropic or transversely isotropic, with
    the volume penalty when ``material.volume_penalty`` > 0. Rotation invariant. ``threads`` > 1: the
    force on that many threads (realtime.threaded). ``precision``: Model.precision."""
    threads = check_threads(threads)
    points, tets = prepare_mesh(points, tets)
    dtype = PRECISIONS[precision]
    btets, geo, prm = block_data(points, tets, material, dtype)
    data = BlockData(btets, geo, prm, np.ones(len(btets), dtype=np.bool_))
    kernel = block_kernel(stvk_force, stvk_energy, partial(block_scratch, dtype), data, len(points), threads)
    return _model(
        "stvk-tm", points, tets, material, loading, *kernel[:3], False, kernel[3], precision=precision, threads=threads
    )


def build_corotational_tm(
    points, tets, material: Material | Materials, loading: Loading | None = None, threads: int = 1
) -> Model:
    """Corotational linear elasticity, polar rotation per tetrahedron (SOFA's "polar" method).

    Isotropic only: for an anisotropic law the rotated-frame force is not the gradient of an energy.
    ``threads`` > 1: the force on that many threads (realtime.threaded).
    """
    threads = check_threads(threads)
    points, tets = prepare_mesh(points, tets)
    if Materials.of(material, len(tets)).transverse:
        raise InputError(
            "corotational-tm: isotropic materials only (the rotated-frame force of an anisotropic "
            "law is not the gradient of an energy); use stvk-tm for fibres"
        )
    btets, geo, prm = block_data(points, tets, material)
    data = BlockData(btets, geo, prm, np.ones(len(btets), dtype=np.bool_))
    kernel = block_kernel(corotational_force, corotational_energy, corotational_scratch, data, len(points), threads)
    return _model("corotational-tm", points, tets, material, loading, *kernel[:3], False, kernel[3], threads=threads)


def build_hybrid_tm(
    points, tets, material: Material | Materials, loading: Loading | None = None, threshold: float | None = None
) -> Model:
    """Linear tensor-mass, StVK on the tetrahedra with a vertex displaced more than ``threshold`` (m); a
    vertex returns to linear within hybrid.RELEASE times it (hysteresis: the force does not switch back
    and forth at the threshold, and damped dynamics settles).

    Default threshold: 10% of the mean edge length, the small-displacement limit of linear elasticity
    quoted by Delingette & Ayache (2004).
    """
    points, tets = prepare_mesh(points, tets)
    tm = TensorMass(points, tets, material)
    if threshold is None:
        e = unique_edges(tets)
        threshold = 0.1 * float(np.linalg.norm(points[e[:, 0]] - points[e[:, 1]], axis=1).mean())
    if not (is_real(threshold) and threshold >= 0.0):
        raise InputError(f"hybrid-tm: threshold = {threshold!r} must be a number >= 0 m")
    btets, geo, prm = block_data(points, tets, material)
    data = HybridData(tm.kernel_data(), btets, geo, prm, np.array([float(threshold), RELEASE * float(threshold)]))
    n_points, n_padded = len(points), len(btets)
    return _model(
        "hybrid-tm",
        points,
        tets,
        material,
        loading,
        hybrid_force,
        hybrid_energy,
        data,
        False,
        lambda: hybrid_scratch(n_points, n_padded),
        tensors=tm,
        threshold=float(threshold),
    )


def nonlinear_fraction(tets: np.ndarray, u: np.ndarray, threshold: float) -> float:
    """Fraction of the tetrahedra (M, 4) int64 that hybrid-tm treats as StVK at displacement u (N, 3) m
    from a fresh start: those with a vertex displaced more than ``threshold`` m (``hybrid_force``'s rule;
    a run that came there may keep more, those within the hysteresis band of hybrid.RELEASE)."""
    moved = np.linalg.norm(u, axis=1) > threshold
    return float(moved[tets].any(axis=1).mean())


def spring_stiffness(points, tets, edges, material: Material | Materials) -> np.ndarray:
    """Van Gelder's calibration (1998): k_ij = sum_{T around ij} E_T V_T / L_ij^2, N/m (E,), E_T the Young's
    modulus of tetrahedron T's material.

    A network of central springs has the Cauchy relation lambda = mu built in (nu = 1/4 for a regular
    lattice): it cannot represent another Poisson's ratio, which is why nu does not appear. The test
    suite measures the resulting Young's modulus and Poisson's ratio of a spring block in uniaxial
    tension and states them.
    """
    from .tensor_mass import LOCAL_EDGES, edge_index

    ev = np.abs(signed_volumes(points, tets)) * Materials.of(material, len(tets)).per_tet("young")
    idx = edge_index(edges, len(points), tets[:, LOCAL_EDGES].reshape(-1, 2)).reshape(-1, 6)
    acc = np.zeros(len(edges))
    np.add.at(acc, idx.ravel(), np.repeat(ev, 6))
    length2 = np.sum((points[edges[:, 1]] - points[edges[:, 0]]) ** 2, axis=1)
    return acc / length2


def build_mass_spring(
    points, tets, material: Material | Materials, loading: Loading | None = None, precision: str = "float64"
) -> Model:
    """Mass-spring network on the mesh edges (Delingette 1998; Liu 2002), lumped FEM masses.

    Damping: the integrators' Rayleigh stiffness term evaluates the spring forces at u + beta v, which
    is a dashpot c = beta k along each spring. ``precision``: Model.precision.
    """
    points, tets = prepare_mesh(points, tets)
    edges = unique_edges(tets)
    k = spring_stiffness(points, tets, edges, material)
    vectors = points[edges[:, 1]] - points[edges[:, 0]]
    dtype = PRECISIONS[precision]
    rest = np.linalg.norm(vectors, axis=1)
    data = SpringData(vectors.astype(dtype), edges, k.astype(dtype), rest.astype(dtype))
    return _model(
        "mass-spring",
        points,
        tets,
        material,
        loading,
        spring_force,
        spring_energy,
        data,
        False,
        rest=spring_rest_stiffness,
        bound=spring_eigenvalue_bound,
        precision=precision,
        stiffness=k,
    )


def _with_quasistatic(model: Model, cls) -> Model:
    """The model with ``cls(model)`` as its quasi-static solver (``cls`` a class with a ``model_name``,
    or a function of the model returning the solver)."""
    extra = dict(model.extra)
    extra["quasistatic"] = solver = cls(model)
    return Model(**{**model.__dict__, "name": solver.model_name, "extra": extra})


def build_precomputed(points, tets, material: Material | Materials, loading: Loading | None = None) -> Model:
    """Quasi-static precomputed linear model (Cotin et al. 1999); see realtime.quasistatic."""
    from .quasistatic import Precomputed

    return _with_quasistatic(build_linear_tm(points, tets, material, loading), Precomputed)


def build_condensed(points, tets, material: Material | Materials, loading: Loading | None = None) -> Model:
    """Static linear model condensed onto the surface (Bro-Nielsen 1996); see realtime.quasistatic."""
    from .quasistatic import Condensed

    return _with_quasistatic(build_linear_tm(points, tets, material, loading), Condensed)


def build_ffd(points, tets, material: Material | Materials, loading: Loading | None = None, degree: int = 3) -> Model:
    """Free-form deformation driven by the tools (Sederberg & Parry 1986; direct manipulation, Hsu et al.
    1992): no mechanics, the non-physics baseline; see realtime.ffd. ``degree``: the lattice's degree per
    axis, its knob ((degree + 1)^3 control points)."""
    from .ffd import FreeFormDeformation, no_energy, no_force

    points, tets = prepare_mesh(points, tets)
    model = _model(
        "ffd",
        points,
        tets,
        material,
        loading,
        no_force,
        no_energy,
        (),
        True,
        rest=lambda m: sp.csr_matrix((3 * m.n_vertices, 3 * m.n_vertices)),
        bound=lambda m: 0.0,
    )
    return _with_quasistatic(model, lambda m: FreeFormDeformation(m, degree))


MODELS: dict[str, Callable[..., Model]] = {
    "linear-tm": build_linear_tm,
    "corotational-tm": build_corotational_tm,
    "stvk-tm": build_stvk_tm,
    "hybrid-tm": build_hybrid_tm,
    "mass-spring": build_mass_spring,
    "precomputed": build_precomputed,
    "condensed": build_condensed,
    "ffd": build_ffd,
    "adaptive-tm": build_adaptive_tm,
}

#: Models that can be built with precision = "float32" (Model.precision). corotational-tm is not among
#: them: its polar decomposition iterates to a float64 tolerance.
FLOAT32_MODELS = ("linear-tm", "stvk-tm", "mass-spring")
#: Models that jump to equilibrium instead of integrating in time (their integrator is QuasiStatic).
QUASI_STATIC = ("precomputed", "condensed", "ffd")
#: Models without mechanics (no internal force, no energy): what a force-field test cannot test.
GEOMETRIC = ("ffd",)


#: The material terms beyond E, nu and rho that each model represents: "fibres" (a transversely
#: isotropic law) and "penalty" (Material.volume_penalty, the incompressibility term of Picinbono et al.
#: 2003). The linear models take fibres in their tensors and have no penalty; adaptive-tm is StVK on its
#: mixed mesh and has both; corotational-tm refuses fibres at build (its rotated-frame force would not
#: be the gradient of an energy); hybrid-tm has the penalty on its StVK tetrahedra only; mass-spring has
#: one stiffness per edge. ffd has no mechanics at all (GEOMETRIC) and claims none. A model runs without
#: what it lacks; ``unrepresented`` names it, and the verification layer says so in every result, table
#: row and report.
REPRESENTS = {
    "linear-tm": ("fibres",),
    "corotational-tm": (),
    "stvk-tm": ("fibres", "penalty"),
    "hybrid-tm": ("fibres",),
    "mass-spring": (),
    "precomputed": ("fibres",),
    "condensed": ("fibres",),
    "ffd": ("fibres", "penalty"),
    "adaptive-tm": ("fibres", "penalty"),
}


def unrepresented(name: str, material: Material | Materials) -> list[str]:
    """What ``material`` asks of model ``name`` that it does not represent (REPRESENTS): one phrase per
    term with the material's value, e.g. "the volume penalty (volume_penalty = 50000 Pa)"."""
    mats = material.materials if isinstance(material, Materials) else (material,)
    asked = {
        "fibres": next((f"the fibres (young_fiber = {m.young_fiber:g} Pa)" for m in mats if m.transverse), None),
        "penalty": next(
            (f"the volume penalty (volume_penalty = {m.volume_penalty:g} Pa)" for m in mats if m.volume_penalty > 0),
            None,
        ),
    }
    return [text for term, text in asked.items() if text is not None and term not in REPRESENTS[name]]


def build_model(
    name: str, points, tets, material: Material | Materials, loading: Loading | None = None, **options
) -> Model:
    """Build the model registered under ``name``. ``options`` go to its builder; ``precision``
    ("float64", the default, or "float32" for FLOAT32_MODELS) is checked here for every model."""
    try:
        builder = MODELS[name]
    except KeyError:
        raise InputError(f"model = {name!r}: must be one of {', '.join(MODELS)}") from None
    precision = options.pop("precision", "float64")
    if precision not in PRECISIONS:
        raise InputError(f"precision = {precision!r}: must be one of {', '.join(PRECISIONS)}")
    if precision != "float64":
        if name not in FLOAT32_MODELS:
            raise InputError(
                f"precision = {precision!r}: {name} runs in float64 only ({', '.join(FLOAT32_MODELS)} run in float32)"
            )
        options["precision"] = precision
    accepted = [k for k in inspect.signature(builder).parameters if k not in ("points", "tets", "material", "loading")]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise InputError(f"{name}: option {unknown[0]!r} is not one of its options ({', '.join(accepted) or 'none'})")
    return builder(np.asarray(points), np.asarray(tets), material, loading, **options)
