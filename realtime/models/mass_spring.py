"""mass-spring: a network of springs on the mesh's edges (Delingette 1998; Liu 2002), calibrated after
Van Gelder (1998)."""

from __future__ import annotations

import numpy as np

from ..geometry import signed_volumes, unique_edges
from ..material import Material, Materials
from ..model import PRECISIONS, Loading, Model, prepare_mesh
from ..springs import SpringData, spring_energy, spring_force
from ..tensor_mass import LOCAL_EDGES, assemble_blocks, edge_index
from .base import ModelSpec, assemble

NAME = "mass-spring"


def spring_stiffness(points, tets, edges, material: Material | Materials) -> np.ndarray:
    """Van Gelder's calibration (1998): k_ij = sum_{T around ij} E_T V_T / L_ij^2, N/m (E,), E_T the Young's
    modulus of tetrahedron T's material.

    A network of central springs has the Cauchy relation lambda = mu built in (nu = 1/4 for a regular
    lattice): it cannot represent another Poisson's ratio, which is why nu does not appear. The test
    suite measures the resulting Young's modulus and Poisson's ratio of a spring block in uniaxial
    tension and states them.
    """
    ev = np.abs(signed_volumes(points, tets)) * Materials.of(material, len(tets)).per_tet("young")
    idx = edge_index(edges, len(points), tets[:, LOCAL_EDGES].reshape(-1, 2)).reshape(-1, 6)
    acc = np.zeros(len(edges))
    np.add.at(acc, idx.ravel(), np.repeat(ev, 6))
    length2 = np.sum((points[edges[:, 1]] - points[edges[:, 0]]) ** 2, axis=1)
    return acc / length2


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


def build(
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
    return assemble(
        NAME,
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


SPEC = ModelSpec(
    name=NAME,
    build=build,
    law="central springs on the mesh's edges, k = sum E V / L^2 (Van Gelder 1998)",
    drops="any Poisson's ratio but the lattice's (about 1/4): a network of central springs obeys Cauchy's lambda = mu",
    float32=True,
    # 30 flops and 32 bytes (two int64 ends, k, L) an edge
    work={"edge": (30.0, 32.0)},
    rank=4,
)
