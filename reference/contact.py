"""Frictionless contact of the body with rigid tools (``reference.problem.RigidTool``) by a penalty, in
dolfinx 0.5.2.

Where a point y = X + u of the body's boundary lies inside a tool, at signed distance g(y) < 0 from the
tool's surface (``gap``), the boundary stores the energy kappa/2 g^2 per unit reference area, so the tool
pushes it out with the traction kappa (-g) grad g. The penalty is kappa = gamma E / h, E the stiffest
material's Young's modulus and h the diameter of the cell under the facet; its error falls as 1/gamma
(the penetration is the pressure over kappa), which the static solve measures by solving again with
gamma four and sixteen times larger (``reference.static``). The contact force and area are integrals over
the boundary at the facets' Gauss points (the area of the penetrated region: a discontinuous
integrand, read with a high quadrature degree).
"""

from __future__ import annotations

import numpy as np
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from mpi4py import MPI
from petsc4py import PETSc

from .problem import RigidTool, ramp

#: gamma of the first solve (kappa = gamma E / h): the penetration is about 1e-3 of a Hertzian
#: indentation's depth (pressure ~ E a / R over kappa, against d = a^2 / R, on cells of h ~ a / 5).
GAMMA = 100.0

#: Each tightening multiplies gamma by this.
TIGHTEN = 4.0


def gap(tool: RigidTool, y, offset):
    """The signed distance (UFL scalar, m) of the point y (UFL vector, m) from the tool's surface with
    the tool moved by ``offset`` (UFL vector, m): negative inside. The same formula as
    ``RigidTool.gap``: a sphere |y - c| - r; a capsule the distance to its segment minus r (the segment's
    parameter clamped to [0, 1]); a plane (y - p) . n."""
    c = ufl.as_vector(list(tool.center)) + offset
    if tool.shape == "plane":
        return ufl.dot(y - c, ufl.as_vector(list(tool.normal)))
    r = y - c
    if tool.shape == "capsule":
        axis = ufl.as_vector([b - a for a, b in zip(tool.center, tool.end, strict=True)])
        t = ufl.max_value(0.0, ufl.min_value(1.0, ufl.dot(r, axis) / ufl.dot(axis, axis)))
        r = r - t * axis
    return ufl.sqrt(ufl.dot(r, r)) - tool.radius


class Contact:
    """The contact terms of a problem's residual, and what they are read as.

    Args:
        domain: the dolfinx mesh.
        tools: the problem's rigid tools.
        young: Pa, the stiffest material's Young's modulus (the penalty's scale).
        degree: the displacement's Lagrange degree (the quadrature of the contact integrals).
        comm: its communicator.
    """

    def __init__(self, domain, tools: tuple[RigidTool, ...], young: float, degree: int, comm):
        self.tools, self.comm, self.domain = tools, comm, domain
        self.gamma = fem.Constant(domain, PETSc.ScalarType(GAMMA))
        self.offsets = [fem.Constant(domain, PETSc.ScalarType((0.0, 0.0, 0.0))) for _ in tools]
        domain.topology.create_connectivity(2, 3)
        facets = dmesh.exterior_facet_indices(domain.topology)
        tags = dmesh.meshtags(domain, 2, facets, np.ones(len(facets), dtype=np.int32))
        boundary = ufl.Measure("ds", domain=domain, subdomain_data=tags)
        self.ds = boundary(1, metadata={"quadrature_degree": 2 * degree + 2})
        self.ds_area = boundary(1, metadata={"quadrature_degree": 8})
        self.kappa = self.gamma * young / ufl.CellDiameter(domain)
        self._read = None  # the force and area forms, compiled on first use

    def _gaps(self, u):
        """[(g, grad g)] of each tool at y = X + u (UFL)."""
        y = ufl.variable(ufl.SpatialCoordinate(self.domain) + u)
        out = []
        for tool, offset in zip(self.tools, self.offsets, strict=True):
            g = gap(tool, y, offset)
            out.append((g, ufl.diff(g, y)))
        return out

    def work(self, u, v):
        """The contact forces' virtual work on v at u, as the residual holds it (N m): the derivative of
        sum_tools integral kappa/2 min(g, 0)^2 ds."""
        form = 0
        for g, grad in self._gaps(u):
            form += self.kappa * ufl.min_value(g, 0.0) * ufl.dot(grad, v) * self.ds
        return form

    def stations(self) -> tuple[float, ...]:
        """The fractions of the travel where the force-indentation curve is read: k / n for k = 1..n, n the
        most ``stations`` any tool asks (none: the end only, which the static solve reads anyway)."""
        n = max(tool.stations for tool in self.tools)
        return tuple(k / n for k in range(1, n + 1)) if n > 1 else ()

    def move(self, s: float) -> None:
        """Every tool at fraction s of its travel."""
        for tool, offset in zip(self.tools, self.offsets, strict=True):
            offset.value = tool.offset(s)

    def move_at(self, t: float) -> None:
        """Every tool where its ramp puts it at time t (s)."""
        for tool, offset in zip(self.tools, self.offsets, strict=True):
            offset.value = tool.offset(ramp(t, tool.ramp, tool.ramp_shape)[0])

    def read(self, u) -> dict:
        """Each tool's force on the body [T][3] N and contact area [T] m^2 at u (lists), on every rank."""
        if self._read is None:
            self._read = []
            for g, grad in self._gaps(u):
                push = -self.kappa * ufl.min_value(g, 0.0)
                force = [fem.form(push * grad[i] * self.ds) for i in range(3)]
                area = fem.form(ufl.conditional(ufl.lt(g, 0.0), 1.0, 0.0) * self.ds_area)
                self._read.append((force, area))

        def total(form) -> float:
            return self.comm.allreduce(fem.assemble_scalar(form), op=MPI.SUM)

        forces = [[total(f) for f in force] for force, _ in self._read]
        areas = [total(area) for _, area in self._read]
        return {"force": forces, "area": areas, "gamma": float(self.gamma.value)}
