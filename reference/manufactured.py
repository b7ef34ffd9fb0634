"""The method of manufactured solutions: the reference's convergence orders against an exact solution
(``manufactured_errors``), for the linear and StVK laws."""

from __future__ import annotations

import numpy as np
import ufl
from dolfinx import fem, geometry
from dolfinx import mesh as dmesh
from mpi4py import MPI
from petsc4py import PETSc

from realtime.material import Material

from .errors import ReferenceSolveError
from .laws import LAWS
from .solver import DIRECT_OPTIONS, Newton


def manufactured_errors(
    law: str, degree: int, n: int, material: Material, comm=MPI.COMM_WORLD, refine: int = 0, points=None
) -> dict:
    """Solve -div P(u) = f on the unit cube (n^3 cubes of six tetrahedra, then ``refine`` uniform
    refinements) with u = u_exact on the boundary, f = -div P(u_exact) derived in UFL, and return the L2
    and H1-seminorm errors; with ``points`` (K, 3), also the solution and u_exact there ("values", "exact").

    u_exact = 0.05 (sin(pi x) sin(pi y) z, x y (1 - z) cos(pi z), sin(pi z) (x + y^2)) is smooth and
    large enough (5% strain) for the StVK terms to matter. Errors are integrated against the exact
    expression with quadrature of degree 2 degree + 6, so that the error of the error is negligible.
    """
    domain = dmesh.create_unit_cube(comm, n, n, n, dmesh.CellType.tetrahedron)
    for _ in range(refine):
        domain.topology.create_entities(1)
        domain = dmesh.refine(domain)
    V = fem.VectorFunctionSpace(domain, ("Lagrange", degree))
    x = ufl.SpatialCoordinate(domain)
    pi = ufl.pi
    ue = 0.05 * ufl.as_vector(
        (
            ufl.sin(pi * x[0]) * ufl.sin(pi * x[1]) * x[2],
            x[0] * x[1] * (1 - x[2]) * ufl.cos(pi * x[2]),
            ufl.sin(pi * x[2]) * (x[0] + x[1] ** 2),
        )
    )
    lam, mu = fem.Constant(domain, PETSc.ScalarType(material.lam)), fem.Constant(domain, PETSc.ScalarType(material.mu))
    a0 = ufl.as_vector((0.0, 0.0, 0.0))

    def P(u):
        F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
        return ufl.diff(LAWS[law](F, lam, mu, a0, 0.0, 0.0), F)

    f = -ufl.div(P(ue))
    u = fem.Function(V)
    v = ufl.TestFunction(V)
    # f is smooth: degree 2 p + 4 integrates it far below the discretisation error (UFL's own estimate
    # for div P(u_exact) of sines asks for thousands of points per cell)
    dxf = ufl.dx(metadata={"quadrature_degree": 2 * degree + 4})
    residual = ufl.inner(P(u), ufl.grad(v)) * dxf - ufl.inner(f, v) * dxf
    fdim = 2
    domain.topology.create_connectivity(fdim, 3)
    facets = dmesh.exterior_facet_indices(domain.topology)
    dofs = fem.locate_dofs_topological(V, fdim, facets)
    g = fem.Function(V)
    g.interpolate(fem.Expression(ue, V.element.interpolation_points()))
    bc = fem.dirichletbc(g, dofs)
    u.x.array[:] = g.x.array  # start from the interpolant: Newton converges in a few steps
    solver = Newton(comm, residual, u, [bc], ufl.derivative(residual, u, ufl.TrialFunction(V)), DIRECT_OPTIONS)
    res = solver.solve(1e-12, 25)
    its, ok = res["iterations"], res["converged"]
    if not ok:
        raise ReferenceSolveError(f"manufactured solution: Newton failed ({law}, P{degree}, n = {n})")
    dx = ufl.dx(metadata={"quadrature_degree": 2 * degree + 6})
    e = u - ue
    l2 = np.sqrt(comm.allreduce(fem.assemble_scalar(fem.form(ufl.inner(e, e) * dx)), op=MPI.SUM))
    h1 = np.sqrt(comm.allreduce(fem.assemble_scalar(fem.form(ufl.inner(ufl.grad(e), ufl.grad(e)) * dx)), op=MPI.SUM))
    out = {
        "h": 1.0 / (n * 2**refine),
        "l2": float(l2),
        "h1": float(h1),
        "dofs": V.dofmap.index_map.size_global * 3,
        "newton_iterations": int(its),
    }
    if points is not None:
        pts = np.ascontiguousarray(points, dtype=np.float64)
        tree = geometry.BoundingBoxTree(domain, 3)
        cells = geometry.compute_colliding_cells(domain, geometry.compute_collisions(tree, pts), pts)
        first = np.array([cells.links(i)[0] for i in range(len(pts))], dtype=np.int32)
        out["values"] = u.eval(pts, first)
        X = pts.T
        out["exact"] = 0.05 * np.stack(
            [
                np.sin(np.pi * X[0]) * np.sin(np.pi * X[1]) * X[2],
                X[0] * X[1] * (1 - X[2]) * np.cos(np.pi * X[2]),
                np.sin(np.pi * X[2]) * (X[0] + X[1] ** 2),
            ],
            axis=1,
        )
    return out
