"""An elasticity problem in dolfinx 0.5.2 (``ProblemForms``): the scene's mesh as a distributed
domain, its spaces, the energy of each material (``reference.laws``) as forms, the constraints and
tools as Dirichlet conditions, the loads, and what a solution is read as (values at points,
reactions), MPI-safe. The solves are ``reference.static`` and ``reference.dynamic``; ``ElasticityProblem``
(``reference.fem``) is the three together.

A port to dolfinx 0.9/0.10 (where VectorFunctionSpace, u.vector and NewtonSolver changed) touches the
reference's dolfinx modules only (this one, ``solver``, ``static``, ``dynamic``, ``manufactured``). The
rest of ``reference`` hands them a mesh, a material and a ``Problem`` and gets numpy arrays back.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import ufl
from dolfinx import fem, geometry
from dolfinx import mesh as dmesh
from mpi4py import MPI
from petsc4py import PETSc

from meshes.regions import locate, spanned
from meshes.tetmesh import TetMesh
from realtime.material import Material, Materials

from .contact import Contact
from .errors import ReferenceSolveError
from .laws import LAWS, volume_penalty_energy
from .problem import Force, Problem, Traction
from .progress import line


def dolfinx_mesh(mesh: TetMesh, comm=MPI.COMM_WORLD, refine: int = 0):
    """A distributed dolfinx mesh of a TetMesh (rank 0 holds the input), refined ``refine`` times
    uniformly (each tetrahedron into eight)."""
    domain_el = ufl.Mesh(ufl.VectorElement("Lagrange", "tetrahedron", 1))
    if comm.rank == 0:
        x, cells = mesh.points, mesh.tets
    else:
        x, cells = np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int64)
    if refine and comm.size > 1:
        # refined on one process, then distributed: dolfinx's parallel refinement picks each octahedron's
        # diagonal by the partition's numbering, and the partition varies from run to run, so the refined
        # mesh, and the answer, did too (5e-5 relative on cantilever-pull's refined P1)
        if comm.rank == 0:
            fine = dolfinx_mesh(mesh, MPI.COMM_SELF, refine)
            x = fine.geometry.x[:, :3].copy()
            cells = fine.geometry.dofmap.array.reshape(-1, 4).astype(np.int64)
        return dmesh.create_mesh(comm, cells, x, domain_el)
    domain = dmesh.create_mesh(comm, cells, x, domain_el)
    for _ in range(refine):
        domain.topology.create_entities(1)
        domain = dmesh.refine(domain)
    return domain


def _marker(region, mesh: TetMesh):
    """A dolfinx marker (x (3, K) -> bool (K,)): the points on the scene mesh's entities spanned by the
    region's vertices (meshes.regions.spanned), so that the reference constrains on its P2 or refined
    mesh exactly what the scene mesh's selection spans, the set the real-time models constrain."""
    selected = region.vertices(mesh)
    return lambda x: spanned(mesh, selected, x.T)


@dataclass
class Solution:
    """What a reference solve returns (numpy arrays on every rank)."""

    values: np.ndarray  # (K, 3) displacement at the requested points, m
    reaction: np.ndarray  # (3,) total force of the tools on the body, N
    info: dict  # dofs, iterations, residuals, timings, solver options


class ProblemForms:
    """An elasticity problem discretised by dolfinx: its forms, conditions and read-outs.

    Args:
        mesh: the scene's TetMesh (the coarse geometry; regions with tags refer to it).
        material: the Material, whose ``law`` picks the energy (linear or stvk); or Materials, one for each
            tetrahedron of ``mesh``: each cell of the (refined) domain then takes the material of the
            scene tetrahedron that holds its midpoint, and integrates that material's own energy, fibres
            and density over its cells (exact per-cell coefficients; ``parts``).
        problem: constraints and loads.
        degree: Lagrange degree, 1 or 2.
        refine: uniform refinements of the mesh before discretising.
        comm: MPI communicator.
        domain: a dolfinx mesh of the body to discretise instead of ``mesh`` refined ``refine`` times (an
            adapted mesh, ``reference.adaptive``): a refinement of ``mesh``, whose regions and materials
            it takes.
    """

    def __init__(
        self,
        mesh: TetMesh,
        material: Material | Materials,
        problem: Problem,
        degree: int = 1,
        refine: int = 0,
        comm=MPI.COMM_WORLD,
        domain=None,
    ):
        self.mesh, self.material, self.problem = mesh, material, problem
        self.degree, self.refine, self.comm = degree, refine, comm
        t0 = time.perf_counter()
        self.domain = dolfinx_mesh(mesh, comm, refine) if domain is None else domain
        self._size = float(np.ptp(mesh.points, axis=0).max())  # m, the body's largest extent
        self.V = fem.VectorFunctionSpace(self.domain, ("Lagrange", degree))
        self.u = fem.Function(self.V, name="displacement")
        self.parts = self._material_parts()
        self.load_factor = fem.Constant(self.domain, PETSc.ScalarType(1.0))
        self._tool_functions = []
        self.load_areas = []  # m^2, the loaded area of each force or traction load
        self._located = None  # the last points evaluate() located, and where (see _locate)
        self._reaction_form = None
        self._det_F = None  # the det F expression of min_det_F
        self.contact = None  # the rigid tools' penalty (reference.contact), made by _residual_form
        self.bcs = self._boundary_conditions()
        self.residual = self._residual_form()
        self.timings = {"setup_s": time.perf_counter() - t0}

    # ---- forms ----

    def _constant(self, value):
        return fem.Constant(self.domain, PETSc.ScalarType(value))

    def _material_parts(self):
        """[(Material, cell measure)]: the whole domain for one Material; for Materials, one subdomain per
        material present, each cell tagged with the material of the scene tetrahedron holding its
        midpoint (a cell of a refined domain lies inside one scene tetrahedron)."""
        if isinstance(self.material, Material):
            return [(self.material, ufl.dx)]
        mats = Materials.of(self.material, self.mesh.n_tets)
        n_local = self.domain.topology.index_map(3).size_local
        cells = np.arange(n_local, dtype=np.int32)
        parent = locate(self.mesh, dmesh.compute_midpoints(self.domain, 3, cells))
        if np.any(parent < 0):
            raise ReferenceSolveError(f"{int(np.sum(parent < 0))} cells of the domain lie in no scene tetrahedron")
        tags = dmesh.meshtags(self.domain, 3, cells, (mats.index[parent] + 1).astype(np.int32))
        dx = ufl.Measure("dx", domain=self.domain, subdomain_data=tags)
        return [(m, dx(k + 1)) for k, m in enumerate(mats.materials) if np.any(mats.index == k)]

    @property
    def linear(self) -> bool:
        """True when every material's energy is quadratic (linear law, no volume penalty) and no rigid
        tool touches the body."""
        return not self.problem.contacts and all(m.law == "linear" and m.volume_penalty == 0.0 for m, _ in self.parts)

    @property
    def law(self) -> str:
        """The law's name: the materials' law, or their laws joined by '+'."""
        return "+".join(sorted({m.law for m, _ in self.parts}))

    def fiber(self, m: Material):
        """The unit fibre direction of material m as a UFL vector: its one direction, or around its axis
        a(x) = axis x (x - point) / |axis x (x - point)| at every quadrature point (the continuous field;
        a law is only evaluated off the axis, where it is defined)."""
        if m.fiber_axis is None:
            return ufl.as_vector(m.fiber_vector.tolist())
        x = ufl.SpatialCoordinate(self.domain)
        t = ufl.cross(ufl.as_vector(list(m.fiber_axis)), x - ufl.as_vector(list(m.fiber_point)))
        return t / ufl.sqrt(ufl.dot(t, t))

    def dx_law(self, m: Material, dx):
        """The measure dx of material m's law integrals. With fibres around an axis the integrand holds a
        non-polynomial field whose UFL degree estimate runs past 20: the StVK residual of constant
        fibres is a polynomial of degree 4 (degree - 1) in the cell, and two more orders integrate the
        field's smooth variation."""
        if m.fiber_axis is None:
            return dx
        return dx(metadata={"quadrature_degree": 4 * (self.degree - 1) + 2})

    def energy_density(self, F, m: Material):
        """Material m's energy per unit reference volume (J/m^3) at the deformation gradient F."""
        psi = LAWS[m.law](
            F, self._constant(m.lam), self._constant(m.mu), self.fiber(m), self._constant(m.dlam), self._constant(m.dmu)
        )
        if m.volume_penalty > 0.0:
            psi += volume_penalty_energy(F, self._constant(m.volume_penalty))
        return psi

    def internal_work(self, u, v, law=None):
        """sum over the materials of the integral of P(F(u)) : grad v, P = dW/dF of each material's
        energy (``law``: a LAWS name to use instead of each material's own, without the penalty)."""
        form = 0
        for m, dx in self.parts:
            F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
            psi = self.energy_density(F, m) if law is None else self._law_only(F, m, law)
            form += ufl.inner(ufl.diff(psi, F), ufl.grad(v)) * self.dx_law(m, dx)
        return form

    def _law_only(self, F, m: Material, law: str):
        return LAWS[law](
            F, self._constant(m.lam), self._constant(m.mu), self.fiber(m), self._constant(m.dlam), self._constant(m.dmu)
        )

    def mass_weighted(self, integrand):
        """sum over the materials of the integral of rho integrand (integrand a scalar UFL form)."""
        return sum(self._constant(m.density) * integrand * dx for m, dx in self.parts)

    def _residual_form(self):
        v = ufl.TestFunction(self.V)
        residual = self.internal_work(self.u, v)
        if self.problem.contacts:
            young = max(m.young for m, _ in self.parts)
            self.contact = Contact(self.domain, self.problem.contacts, young, self.degree, self.comm)
            self.contact.move(1.0)
            residual += self.contact.work(self.u, v)
        g = self.problem.gravity()
        if np.any(g != 0.0):
            residual -= self.load_factor * self.mass_weighted(ufl.inner(self._constant(tuple(g)), v))
        surface_loads = [ld for ld in self.problem.loads if isinstance(ld, (Force, Traction))]
        if surface_loads:
            fdim = 2
            self.domain.topology.create_connectivity(fdim, 3)
            facets, values = [], []
            boundary = dmesh.exterior_facet_indices(self.domain.topology)
            centres = dmesh.compute_midpoints(self.domain, fdim, boundary)
            for k, ld in enumerate(surface_loads, start=1):
                # a boundary facet is loaded when its scene-mesh parent face has its three vertices in the
                # region: the face the engine loads (a facet's centroid lies inside its parent face)
                f = boundary[spanned(self.mesh, ld.region.vertices(self.mesh), centres)]
                facets.append(f)
                values.append(np.full(len(f), k, dtype=np.int32))
            facets = np.concatenate(facets)
            order = np.argsort(facets)
            tags = dmesh.meshtags(self.domain, fdim, facets[order], np.concatenate(values)[order])
            ds = ufl.Measure("ds", domain=self.domain, subdomain_data=tags)
            for k, ld in enumerate(surface_loads, start=1):
                area = self.comm.allreduce(fem.assemble_scalar(fem.form(self._constant(1.0) * ds(k))), op=MPI.SUM)
                self.load_areas.append(area)
                if area <= 0.0:
                    raise ReferenceSolveError(
                        f"{type(ld).__name__.lower()} load {ld.region.describe()}: no boundary face in the region"
                    )
                t = np.asarray(ld.value, dtype=float)
                if isinstance(ld, Force):
                    t = t / area  # a total force spread as a uniform traction
                residual -= self.load_factor * ufl.inner(self._constant(tuple(t)), v) * ds(k)
        return residual

    # ---- boundary conditions ----

    def _component_dofs(self, region, c):
        Vc, _ = self.V.sub(c).collapse()
        dofs = fem.locate_dofs_geometrical((self.V.sub(c), Vc), _marker(region, self.mesh))
        return Vc, dofs

    def _boundary_conditions(self):
        bcs = []
        for fx in self.problem.fixed:
            for c, name in enumerate("xyz"):
                if name in fx.components:
                    Vc, dofs = self._component_dofs(fx.region, c)
                    zero = fem.Function(Vc)
                    bcs.append(fem.dirichletbc(zero, dofs, self.V.sub(c)))
        self.tool_dofs = []
        self._tool_points = []  # (tool, component, dofs in V, their rest points (K, 3))
        nodes = self.V.tabulate_dof_coordinates()
        for tool in self.problem.tools:
            for c, name in enumerate("xyz"):
                if name in tool.components:
                    Vc, dofs = self._component_dofs(tool.region, c)
                    g = fem.Function(Vc)
                    self._tool_functions.append((tool, c, g))
                    bcs.append(fem.dirichletbc(g, dofs, self.V.sub(c)))
                    d = np.asarray(dofs[0])
                    self.tool_dofs.append((c, d))
                    self._tool_points.append((tool, c, d, nodes[d // 3]))
        self.set_tool_fraction(1.0)
        return bcs

    def set_tool_fraction(self, s: float) -> None:
        """Move every tool to fraction s of its final displacement (angle, for rotations), the rigid
        tools to fraction s of their travel."""
        for tool, c, g in self._tool_functions:
            g.interpolate(lambda x, tool=tool, c=c: tool.at_fraction(x.T, s)[:, c])
        if self.contact is not None:
            self.contact.move(s)

    def rigid_body_modes(self):
        """The six rigid-body modes as a PETSc near null space (GAMG's coarse space for elasticity)."""
        x = self.V.tabulate_dof_coordinates()
        vecs = [fem.Function(self.V) for _ in range(6)]
        for k in range(3):
            vecs[k].x.array.reshape(-1, 3)[:, k] = 1.0
        rot = [(0, 1), (1, 2), (2, 0)]
        for k, (i, j) in enumerate(rot):
            arr = vecs[3 + k].x.array.reshape(-1, 3)
            arr[:, i] = -x[:, j]
            arr[:, j] = x[:, i]
        petsc_vecs = []
        for v in vecs:
            v.x.scatter_forward()
            # a copy owns its memory: v.vector wraps the Function's array, which dies with this frame
            petsc_vecs.append(v.vector.copy())
        return PETSc.NullSpace().create(vectors=_orthonormal(petsc_vecs), comm=self.comm)

    def energy(self) -> float:
        """Total elastic energy of the current displacement, J (MPI-reduced)."""
        F = ufl.Identity(3) + ufl.grad(self.u)
        energy = sum(self.energy_density(F, m) * self.dx_law(m, dx) for m, dx in self.parts)
        local = fem.assemble_scalar(fem.form(energy))
        return self.comm.allreduce(local, op=MPI.SUM)

    def set_tool_fraction_at(self, t: float) -> None:
        """Move every tool to where its ramp puts it at time t (s)."""
        for tool, c, g in self._tool_functions:
            g.interpolate(lambda x, tool=tool, c=c: tool.value(x.T, t)[:, c])
        if self.contact is not None:
            self.contact.move_at(t)

    def start_from(self, coarse: ProblemForms) -> None:
        """Set u to another problem's solution evaluated at this one's nodes (nested iteration: the
        refined problem starts where the coarse one ended). Collective: in parallel every rank's nodes
        (owned and ghosts) are gathered, evaluated on the coarse problem's distributed mesh by all
        ranks, and each rank takes its own back. On the same mesh (P3 from P2) the solution is interpolated:
        exact, since the coarser degree's space lies in the finer's."""
        if coarse.domain is self.domain:
            self.u.interpolate(coarse.u)
            self.u.x.scatter_forward()
            return
        nodes = self.V.tabulate_dof_coordinates()
        if self.comm.size == 1:
            self.u.x.array[:] = coarse.evaluate(nodes).ravel()
            return
        counts = self.comm.allgather(len(nodes))
        values = coarse.evaluate(np.concatenate(self.comm.allgather(nodes)))
        start = sum(counts[: self.comm.rank])
        self.u.x.array[:] = values[start : start + len(nodes)].ravel()

    def min_det_F(self) -> float:
        """The smallest det F = det(I + grad u) at the vertices and centroids of the cells (MPI-reduced).
        For P1 it is exact (F is constant per cell); for P2, det F is a cubic and these five points sample it."""
        if self._det_F is None:  # compiled once per problem, evaluated after every load step
            points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.25, 0.25, 0.25]], dtype=np.float64)
            self._det_F = fem.Expression(ufl.det(ufl.Identity(3) + ufl.grad(self.u)), points)
        n_local = self.domain.topology.index_map(3).size_local
        local = self._det_F.eval(np.arange(n_local, dtype=np.int32)).min() if n_local else np.inf
        return float(self.comm.allreduce(float(local), op=MPI.MIN))

    def _log(self, msg: str) -> None:
        """Progress to stderr, from rank 0 only, one whole line (reference.progress)."""
        line(msg, self.comm.rank)

    # ---- post-processing (MPI-safe) ----

    @property
    def n_dofs(self) -> int:
        return self.V.dofmap.index_map.size_global * self.V.dofmap.index_map_bs

    def _locate(self, pts: np.ndarray) -> tuple:
        """Where this rank evaluates each of ``pts`` (K, 3) m: (points, local cells) for the points inside
        its cells, the same for the points that round-off puts a hair outside every cell (the closest
        cell within 1e-9 of the mesh's size: a refined mesh's boundary midpoint against the coarse
        cells), and the number of ranks that evaluate each point (K,). Kept for the last point set: a
        dynamic solve evaluates the same points at every output."""
        if self._located is not None and np.array_equal(self._located[0], pts):
            return self._located[1]
        tree = geometry.BoundingBoxTree(self.domain, 3)
        cand = geometry.compute_collisions(tree, pts)
        cells = geometry.compute_colliding_cells(self.domain, cand, pts)
        found = np.array([len(cells.links(i)) > 0 for i in range(len(pts))], dtype=bool)
        inside = np.flatnonzero(found)
        first = np.array([cells.links(i)[0] for i in inside], dtype=np.int32)
        count = np.zeros(len(pts))
        self.comm.Allreduce(found.astype(float), count, op=MPI.SUM)
        missing = np.flatnonzero(count == 0)
        near_idx, near_cells = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int32)
        if len(missing):
            at = pts[missing]
            closest, near = self._closest_candidates(cand, missing, at)
            check = np.flatnonzero((closest >= 0) & ~near)
            if len(check):
                d2 = geometry.squared_distance(self.domain, 3, closest[check], at[check])
                near[check] = d2 <= (1e-9 * self._size) ** 2
            hits = np.zeros(len(missing))
            self.comm.Allreduce(near.astype(float), hits, op=MPI.SUM)
            count[missing] = hits
            near_idx, near_cells = missing[near], closest[near].astype(np.int32)
        if np.any(count == 0):
            bad = int(np.argmax(count == 0))
            raise ReferenceSolveError(f"point {bad} {pts[bad]} lies outside the reference mesh")
        where = (inside, first, near_idx, near_cells, count)
        self._located = (pts.copy(), where)
        return where

    def _closest_candidates(self, cand, missing: np.ndarray, at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For the points ``at`` (K, 3) m that GJK put in no cell of this rank (the ``missing`` indices
        into the collision candidates ``cand``): the candidate cell (its bounding box holds the point) the
        point is deepest in by its barycentric coordinates, and whether it lies in it to 1e-9 of a
        coordinate. GJK's distance is off by about 1e-9 m near a vertex: a point nudged 2e-9 m off a corner
        of a refined grid (a staged scene's vertex) lay in none of the six cells around it by GJK, at
        8.8e-10 m from each. A point outside every box (a hair outside the mesh) gets the cell whose
        midpoint is nearest, unaccepted here (the caller measures its distance). Returns (cells (K,) int32,
        -1 where none; inside (K,) bool)."""
        out, inside = np.full(len(missing), -1, dtype=np.int32), np.zeros(len(missing), dtype=bool)
        x, dofmap = self.domain.geometry.x, self.domain.geometry.dofmap
        for k, i in enumerate(missing):
            cells = np.asarray(cand.links(int(i)), dtype=np.int32)
            if not len(cells):
                continue
            v = x[np.array([dofmap.links(c) for c in cells])]  # (C, 4, 3): affine tetrahedra
            lam = np.linalg.solve(np.swapaxes(v[:, 1:] - v[:, :1], 1, 2), (at[k] - v[:, 0])[:, :, None])[:, :, 0]
            lam = np.column_stack([1.0 - lam.sum(axis=1), lam])
            best = int(np.argmax(lam.min(axis=1)))
            out[k], inside[k] = cells[best], lam[best].min() >= -1e-9
        n_local = self.domain.topology.index_map(3).size_local
        rest = np.flatnonzero(out < 0)
        if len(rest) and n_local:
            own = np.arange(n_local, dtype=np.int32)
            tree = geometry.BoundingBoxTree(self.domain, 3)
            midpoints = geometry.create_midpoint_tree(self.domain, 3, own)
            out[rest] = geometry.compute_closest_entity(tree, midpoints, self.domain, at[rest])
        return out, inside

    def evaluate(self, points: np.ndarray, function=None) -> np.ndarray:
        """Values (K, 3) of the displacement at points (K, 3) m, on every rank.

        Each rank evaluates the points inside its cells; a sum over ranks with a count divides out the
        points found on two ranks (the field is continuous, so their values agree).
        """
        u = self.u if function is None else function
        pts = np.ascontiguousarray(points, dtype=np.float64)
        inside, first, near_idx, near_cells, count = self._locate(pts)
        vals = np.zeros((len(pts), 3))
        if len(inside):
            vals[inside] = u.eval(pts[inside], first)
        if len(near_idx):
            vals[near_idx] = u.eval(pts[near_idx], near_cells)
        total = np.zeros_like(vals)
        self.comm.Allreduce(vals, total, op=MPI.SUM)
        return total / count[:, None]

    def reaction(self) -> np.ndarray:
        """Total force (3,) N the tools exert on the body: the residual summed over their dofs, and the
        rigid tools' contact forces (``Contact.read``, with the penalty in use)."""
        rigid = np.zeros(3)
        if self.contact is not None:
            rigid = np.sum(np.asarray(self.contact.read(self.u)["force"]), axis=0)
        if not self.tool_dofs:
            return rigid
        if self._reaction_form is None:  # compiled once: a dynamic solve asks at every output
            self._reaction_form = fem.form(self.residual)
        r = fem.petsc.assemble_vector(self._reaction_form)
        r.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        arr = r.array_r
        n_owned = self.V.dofmap.index_map.size_local * self.V.dofmap.index_map_bs
        out = np.zeros(3)
        seen = set()
        for c, dofs in self.tool_dofs:
            own = dofs[dofs < n_owned]
            new = [d for d in own if d not in seen]  # a vertex in two tools counts once
            seen.update(new)
            out[c] += float(np.sum(arr[np.asarray(new, dtype=np.int64)])) if new else 0.0
        return self.comm.allreduce(out, op=MPI.SUM) + rigid

    def stiffness_matrix(self):
        """Serial only: the stiffness at u = 0 without boundary conditions as scipy CSR, and the dof
        coordinates (n_dofs / 3, 3) in dolfinx's node order (dof 3 k + c is node k, component c)."""
        import scipy.sparse as sp

        if self.comm.size != 1:
            raise RuntimeError("stiffness_matrix is serial")
        du = ufl.TrialFunction(self.V)
        zero = fem.Function(self.V)
        a = ufl.replace(ufl.derivative(self.residual, self.u, du), {self.u: zero})
        A = fem.petsc.assemble_matrix(fem.form(a))
        A.assemble()
        indptr, indices, data = A.getValuesCSR()
        K = sp.csr_matrix((data, indices, indptr), shape=A.getSize())
        return K, self.V.tabulate_dof_coordinates()

    def residual_vector(self, u_nodes: np.ndarray | None = None):
        """Serial only: residual (internal minus external force, N) at the dolfinx node order, (n, 3).
        If ``u_nodes`` (n, 3) m is given it is loaded into u first (node order of dof coordinates)."""
        if self.comm.size != 1:
            raise RuntimeError("residual_vector is serial")
        if u_nodes is not None:
            self.u.x.array[:] = np.asarray(u_nodes, dtype=float).ravel()
        r = fem.petsc.assemble_vector(fem.form(self.residual))
        r.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return r.array_r.reshape(-1, 3).copy()


def _orthonormal(vecs):
    """Modified Gram-Schmidt on PETSc vectors (in place); returns them."""
    for i, v in enumerate(vecs):
        for u in vecs[:i]:
            v.axpy(-v.dot(u), u)
        v.normalize()
    return vecs
