"""Every derived elastic constant tested by the experiment that defines it, on both sides separately.

The engine (``realtime.laws``, numba) and the reference (``reference.laws``, UFL) share only the
``Material`` that converts a scene's constants into Lame and fibre coefficients: a conversion wrong in
that one place is wrong on both sides at once, and no comparison of the two could see it. So each side's
stress response is probed here as a testing machine would probe a specimen, and compared with the
constant the scene gave:

- Young's modulus and Poisson's ratio: uniaxial stress (every other stress component zero), E = s / e
  along the load and nu = -(lateral strain) / e;
- a shear modulus: simple shear, G = tau / gamma;
- ``young_fiber``: uniaxial stress along the fibre; the fibre-plane shear modulus mu + fiber_shear / 2
  and the transverse modulus across the fibre, whose closed forms are derived below from the energy.

The probes are small strains (1e-7) about the rest state, where both laws reduce to linear elasticity:
a finite-difference error of order 1e-7 relative, hence the 1e-5 tolerances.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from realtime import laws
from realtime.material import Material

H = 1e-7  # probe strain
VOIGT = [(0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1)]

MATERIALS = {
    "isotropic": Material(2.8e4, 0.4, 1000.0),
    "fibre, no fibre shear": Material(1e4, 0.3, 1000.0, fiber=(1.0, 0.0, 0.0), young_fiber=1.9e4),
    "fibre with fibre shear": Material(1e4, 0.3, 1000.0, fiber=(1.0, 0.0, 0.0), young_fiber=9e3, fiber_shear=3e3),
    "oblique fibre, negative fibre shear": Material(
        5e3, 0.45, 1000.0, fiber=(1.0, 2.0, 2.0), young_fiber=4e4, fiber_shear=-2e3
    ),
}


def engine_stress(law: str, m: Material):
    """sigma(F) (3, 3) Pa of the engine's law (first Piola-Kirchhoff, = Cauchy to first order)."""
    pk1 = {"linear": laws.linear_pk1, "stvk": laws.stvk_pk1}[law]
    return lambda F: pk1(F, m.lam, m.mu, m.fiber_vector, m.dlam, m.dmu)


def reference_stress(law: str, m: Material):
    """sigma(F) of the reference's UFL law: P = dW/dF evaluated by dolfinx on a one-cell mesh whose
    displacement (F - I) x is interpolated exactly."""
    import ufl
    from dolfinx import fem
    from dolfinx import mesh as dmesh
    from mpi4py import MPI

    from reference.laws import LAWS

    domain = dmesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1, dmesh.CellType.tetrahedron)
    V = fem.VectorFunctionSpace(domain, ("Lagrange", 1))
    u = fem.Function(V)
    F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
    a = ufl.as_vector(m.fiber_vector.tolist())
    P = ufl.diff(LAWS[law](F, m.lam, m.mu, a, m.dlam, m.dmu), F)
    expr = fem.Expression(P, np.array([[0.25, 0.25, 0.25]]))

    def stress(Fnum):
        G = np.asarray(Fnum) - np.eye(3)
        u.interpolate(lambda x: G @ x)
        return expr.eval(np.array([0], dtype=np.int32)).reshape(3, 3)

    return stress


def rotation_to(d: np.ndarray) -> np.ndarray:
    """A rotation Q (3, 3) whose first column is the unit vector d."""
    d = d / np.linalg.norm(d)
    helper = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
    e2 = np.cross(d, helper)
    e2 /= np.linalg.norm(e2)
    return np.stack([d, e2, np.cross(d, e2)], axis=1)


def probe(stress, Q: np.ndarray) -> np.ndarray:
    """The 6x6 response (Voigt, engineering shears) in the frame Q: column k is the stress in that frame
    for a strain H in the frame's k-th component."""
    R = np.zeros((6, 6))
    for k, (i, j) in enumerate(VOIGT):
        eps = np.zeros((3, 3))
        eps[i, j] = eps[j, i] = H if i == j else H / 2
        s = Q.T @ stress(np.eye(3) + Q @ eps @ Q.T) @ Q
        R[:, k] = [s[p, q] for p, q in VOIGT]
    return R / H


def uniaxial(stress, direction) -> tuple[float, float]:
    """Uniaxial stress along ``direction``: the Young's modulus and the largest lateral contraction
    ratio (Poisson's ratio for an isotropic law)."""
    strain = np.linalg.solve(probe(stress, rotation_to(np.asarray(direction, float))), np.eye(6)[0])
    return 1.0 / strain[0], float(-min(strain[1], strain[2]) / strain[0])


def simple_shear(stress, d1, d2) -> float:
    """Shear modulus tau / gamma for a simple shear of d1 along d2 (two orthogonal unit vectors), the
    other strains held at zero (the tangent at rest of a homogeneous simple shear)."""
    d1, d2 = np.asarray(d1, float), np.asarray(d2, float)
    F = np.eye(3) + H * np.outer(d1, d2)
    return float(d1 @ stress(F) @ d2) / H


def transverse_modulus(m: Material) -> float:
    """Closed form, from the energy, of the modulus across the fibre (uniaxial stress along e2 with the
    fibre along e1): the stress balance  s11 = lam t + (2 mu + dlam + 2 dmu) e11 = 0,
    s22 = lam t + 2 mu e22 = s, s33 = lam t + 2 mu e33 = 0 with t = e11 + e22 + e33."""
    lam, mu, k = m.lam, m.mu, 2 * m.mu + m.dlam + 2 * m.dmu
    A = np.array([[lam + k, lam, lam], [lam, lam + 2 * mu, lam], [lam, lam, lam + 2 * mu]])
    e = np.linalg.solve(A, [0.0, 1.0, 0.0])
    return 1.0 / e[1]


SIDES = {"engine": engine_stress, "reference": reference_stress}


@pytest.mark.parametrize("side", SIDES)
@pytest.mark.parametrize("law", ["linear", "stvk"])
@pytest.mark.parametrize("name", MATERIALS)
def test_constants_by_their_defining_experiment(side, law, name):
    m = MATERIALS[name]
    stress = SIDES[side](law, m)
    if m.fiber is None:
        E, nu = uniaxial(stress, [1.0, 0.3, -0.2])
        assert E == pytest.approx(m.young, rel=1e-5)
        assert nu == pytest.approx(m.poisson, rel=1e-5)
        assert simple_shear(stress, [1, 0, 0], [0, 1, 0]) == pytest.approx(m.young / (2 * (1 + m.poisson)), rel=1e-5)
        return
    a = m.fiber_vector
    Q = rotation_to(a)
    b, c = Q[:, 1], Q[:, 2]  # two directions across the fibre
    E_fibre, _ = uniaxial(stress, a)
    assert E_fibre == pytest.approx(m.young_fiber, rel=1e-5)
    assert uniaxial(stress, b)[0] == pytest.approx(transverse_modulus(m), rel=1e-5)
    mu = m.young / (2 * (1 + m.poisson))
    assert simple_shear(stress, a, b) == pytest.approx(mu + m.fiber_shear / 2, rel=1e-5)  # in a fibre plane
    assert simple_shear(stress, b, c) == pytest.approx(mu, rel=1e-5)  # across the fibre


def test_a_bar_pulled_along_its_fibre_carries_young_fiber():
    """The finding that started this file: with fiber_shear = 3 kPa a bar pulled along its fibre used to
    carry 1.15 x young_fiber x strain. The whole reference (P1, linear law: uniaxial stress is a linear
    field, so exact) pulls a bar on rollers by 0.1% and the tool's reaction is read back."""
    from meshes import structured_box
    from meshes.regions import BoxRegion
    from reference.fem import ElasticityProblem
    from reference.problem import Displacement, Fixed, Problem

    L, W, T = 0.04, 0.01, 0.01
    mesh = structured_box([L, W, T], [4, 1, 1])
    eps = 1e-9
    face = lambda axis, at: BoxRegion(  # noqa: E731
        tuple(at - eps if k == axis else -1.0 for k in range(3)),
        tuple(at + eps if k == axis else 1.0 for k in range(3)),
    )
    for m in (MATERIALS["fibre with fibre shear"], MATERIALS["isotropic"]):
        m = m.replace(law="linear")
        problem = Problem(
            fixed=(Fixed(face(0, 0.0), ("x",)), Fixed(face(1, 0.0), ("y",)), Fixed(face(2, 0.0), ("z",))),
            loads=(Displacement(face(0, L), ("x",), translation=(1e-3 * L, 0.0, 0.0)),),
        )
        ep = ElasticityProblem(mesh, m, problem, degree=1)
        ep.solve()
        modulus = ep.reaction()[0] / (W * T) / 1e-3
        expected = m.young_fiber if m.fiber is not None else m.young
        # a direct solve of a field P1 represents exactly: round-off of the condition number, 1e-9
        assert modulus == pytest.approx(expected, rel=1e-9)
        assert math.isfinite(modulus)
