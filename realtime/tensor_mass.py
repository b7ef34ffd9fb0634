"""Linear tensor-mass model (Cotin, Delingette & Ayache 2000; Delingette & Ayache 2004, sec. 3).

The P1 stiffness of a tetrahedron T couples its vertices a, b through the 3x3 block

    K^T_ab = V_T  sum_qs C_pqrs  g_a,q  g_b,s            (p, r the block's row and column)

with g_a the gradient of the barycentric function of vertex a and C the linear elasticity tensor
(isotropic: K_ab = V (lam g_a g_b^T + mu g_b g_a^T + mu (g_a . g_b) I)). Summing over the tetrahedra
around a vertex gives the *vertex tensor* T_ii and around an edge (i < j) the *edge tensor* T_ij; the
internal force is

    f_i = -T_ii u_i - sum_{j > i} T_ij u_j - sum_{j < i} T_ji^T u_j

i.e. f = -K u with K the assembled P1 stiffness, stored once per edge (half of a symmetric block
sparse matrix). The tensors are kept per tetrahedron too, so that removing tetrahedra (cutting)
subtracts exactly their contribution from the touched vertices and edges.

The kernel evaluates the same force in difference form. Each element's stiffness annihilates
translations, so every block row of K sums to zero, T_ii = -sum_{j != i} K_ij, and

    f_i = -sum_{j > i} T_ij (u_j - u_i) - sum_{j < i} T_ji^T (u_j - u_i)

which never reads the vertex tensors. The sum above cancels: for a smooth u, |K u| is smaller than
|K| |u| by about the square of the number of elements across the body, and each product loses that
many leading digits (in float32, a 2000-step run on a cube drifted 2.9e-5 from float64). The terms of
the difference form are as small as the differences, so only the cancellation between the edges'
terms is left, one factor of that number instead of two (the same run: 2.2e-7).
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
import scipy.sparse as sp

from .blocks import U1, U2, U3, U4, U5, U6, U7, U8, U9
from .errors import InputError
from .geometry import shape_gradients, signed_volumes, unique_edges
from .laws import linear_elasticity_tensor
from .material import Material, Materials

_JIT = dict(nogil=True, cache=True)
_HOT = dict(nogil=True, cache=True, fastmath={"contract", "reassoc", "nsz", "arcp"})  # see blocks.HOT

#: Local edges of a tetrahedron, in the order of TetraTensors.tet_edges' columns.
LOCAL_EDGES = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])


def element_stiffness(points: np.ndarray, tets: np.ndarray, material: Material | Materials) -> np.ndarray:
    """P1 linear stiffness blocks of every tetrahedron, (M, 4, 4, 3, 3) float64, N/m.

    ke[e, a, b] is the 3x3 block coupling local vertex a (rows) to local vertex b (columns); each
    tetrahedron takes its own material's tensor (``material`` a Material, or Materials with one per
    tetrahedron).
    """
    mats = Materials.of(material, len(tets))
    grads, vol = shape_gradients(points, tets)
    if len(mats.materials) == 1 and mats.materials[0].fiber_axis is None:  # one tensor for the whole mesh
        m = mats.materials[0]
        C = linear_elasticity_tensor(m.lam, m.mu, m.fiber_vector, m.dlam, m.dmu)
        return np.einsum("e,pqrs,eaq,ebs->eabpr", vol, C, grads, grads, optimize=True)
    C = element_elasticity(points, tets, mats)
    return np.einsum("e,epqrs,eaq,ebs->eabpr", vol, C, grads, grads, optimize=True)


def element_elasticity(points: np.ndarray, tets: np.ndarray, material: Material | Materials, penalty: bool = False):
    """The elasticity tensor of every tetrahedron, (M, 3, 3, 3, 3) Pa: its material's, the fibre direction
    taken at the centroid (``Material.fiber_directions``); with ``penalty``, the volume penalty's
    stiffness at rest (its coefficient added to lambda)."""
    mats = Materials.of(material, len(tets))
    a = mats.fiber_directions(points[tets].mean(axis=1))
    lam = mats.per_tet("lam") + (mats.per_tet("volume_penalty") if penalty else 0.0)
    shape = (-1, 1, 1, 1, 1)
    return linear_elasticity_tensor(
        lam.reshape(shape),
        mats.per_tet("mu").reshape(shape),
        a,
        mats.per_tet("dlam").reshape(shape),
        mats.per_tet("dmu").reshape(shape),
    )


def edge_index(edges: np.ndarray, n_vertices: int, pairs: np.ndarray) -> np.ndarray:
    """Index into ``edges`` (E, 2 sorted) of each vertex pair (K, 2); -1 where no such edge."""
    lo = np.minimum(pairs[:, 0], pairs[:, 1]).astype(np.int64)
    hi = np.maximum(pairs[:, 0], pairs[:, 1]).astype(np.int64)
    keys = edges[:, 0] * n_vertices + edges[:, 1]
    want = lo * n_vertices + hi
    pos = np.searchsorted(keys, want)
    pos = np.minimum(pos, len(keys) - 1)
    return np.where(keys[pos] == want, pos, -1)


def assemble_blocks(rows: np.ndarray, cols: np.ndarray, blocks: np.ndarray, n: int) -> sp.csr_matrix:
    """Sum 3x3 blocks (K, 3, 3) N/m at block positions (rows, cols) (K,) int into a (3n, 3n) CSR
    matrix (dof 3 i + c); repeated positions add up."""
    r = (3 * rows[:, None, None] + np.arange(3)[None, :, None]).repeat(3, axis=2)
    c = (3 * cols[:, None, None] + np.arange(3)[None, None, :]).repeat(3, axis=1)
    return sp.coo_matrix((blocks.ravel(), (r.ravel(), c.ravel())), shape=(3 * n, 3 * n)).tocsr()


@nb.njit(**_JIT)
def scatter_blocks(vertex_tensors, edge_tensors, tets, tet_edges, ke, which, sign, local_edges):
    """vertex_tensors (N, 3, 3) and edge_tensors (E, 3, 3) N/m += sign x the element blocks ke (M, 4, 4,
    3, 3) N/m of tetrahedra ``which`` (K,) int64: K_aa to vertex tets[e, a], and to edge tet_edges[e, k]
    (local edge k = (a, b) of local_edges (6, 2)) K_ab where tets[e, a] < tets[e, b], else K_ba = K_ab^T
    (the edge's block is (lo, hi))."""
    for w in range(which.shape[0]):
        e = which[w]
        for a in range(4):
            v = tets[e, a]
            for i in range(3):
                for j in range(3):
                    vertex_tensors[v, i, j] += sign * ke[e, a, a, i, j]
        for k in range(6):
            a, b = local_edges[k, 0], local_edges[k, 1]
            if tets[e, a] > tets[e, b]:
                a, b = b, a
            g = tet_edges[e, k]
            for i in range(3):
                for j in range(3):
                    edge_tensors[g, i, j] += sign * ke[e, a, b, i, j]


@nb.njit(**_JIT)
def remove_blocks(vertex_tensors, edge_tensors, tets, tet_edges, ke, which, local_edges, valence, alive):
    """A cut's update of the tensors in one compiled call: ``scatter_blocks`` with sign -1 for tetrahedra
    ``which`` (K,) int64, each of their vertices' count of alive tetrahedra valence (N,) int64 less one,
    and alive (M,) bool False for them."""
    scatter_blocks(vertex_tensors, edge_tensors, tets, tet_edges, ke, which, -1.0, local_edges)
    for w in range(which.shape[0]):
        e = which[w]
        alive[e] = False
        for a in range(4):
            valence[tets[e, a]] -= 1


class TensorData(NamedTuple):
    """linear_tm_force's data: vertex_tensors (N, 3, 3) N/m, cols (E,) int64 (the larger end j of each edge),
    edge_tensors (E, 3, 3) N/m, row_start (N + 1,) int64 (the edges (i, j > i) of vertex i are
    row_start[i]:row_start[i + 1])."""

    vertex_tensors: np.ndarray
    cols: np.ndarray
    edge_tensors: np.ndarray
    row_start: np.ndarray


class TensorMass:
    """Vertex and edge stiffness tensors of a tetrahedral mesh.

    Attributes:
        n_vertices: N.
        edges: (E, 2) int64, edges[:, 0] < edges[:, 1].
        vertex_tensors: (N, 3, 3) float64, N/m: T_ii.
        edge_tensors: (E, 3, 3) float64, N/m: T_ij for edge (i, j), i < j.
        tet_edges: (M, 6) int64, the edge index of each local edge (LOCAL_EDGES order).
        ke: (M, 4, 4, 3, 3) float64, the element blocks, kept for local updates (cutting).
        volumes: (M,) float64, m^3, each tetrahedron's rest volume.
        materials: the Materials of the M tetrahedra.
        generation: the number of cuts made (``remove`` calls).
    """

    def __init__(self, points: np.ndarray, tets: np.ndarray, material: Material | Materials):
        self.n_vertices = len(points)
        self.tets = np.asarray(tets, dtype=np.int64)
        self.materials = Materials.of(material, len(self.tets))
        self.edges = unique_edges(self.tets)
        self.ke = element_stiffness(points, self.tets, self.materials)
        self.volumes = np.abs(signed_volumes(points, self.tets))  # (M,) m^3: a cut's masses read them
        pairs = self.tets[:, LOCAL_EDGES]  # (M, 6, 2)
        self.tet_edges = edge_index(self.edges, self.n_vertices, pairs.reshape(-1, 2)).reshape(-1, 6)
        self.vertex_tensors = np.zeros((self.n_vertices, 3, 3))
        self.edge_tensors = np.zeros((len(self.edges), 3, 3))
        self._scatter(np.arange(len(self.tets)), +1.0)
        self.generation = 0  # cuts made: a model built at an older generation holds outdated masses

    def _scatter(self, which: np.ndarray, sign: float) -> None:
        """Add (sign=+1) or remove (sign=-1) the blocks of tetrahedra ``which`` (K,) int: compiled, so
        that a cut of one tetrahedron costs microseconds (ten numpy ``add.at`` calls took 40 us)."""
        scatter_blocks(self.vertex_tensors, self.edge_tensors, self.tets, self.tet_edges, self.ke,
                       np.asarray(which, dtype=np.int64), float(sign), LOCAL_EDGES)  # fmt: skip

    def remove(self, which) -> np.ndarray:
        """Cut: remove tetrahedra ``which`` (K,) int, updating only the tensors of their vertices and
        edges (Cotin et al. 2000). An edge left with no tetrahedron keeps a zero tensor. Returns the
        tetrahedra removed, sorted and once each (K',) int64."""
        which = np.unique(np.asarray(which, dtype=np.int64))
        alive = self.alive
        if not alive[which].all():
            bad = int(which[~alive[which]][0])
            raise InputError(f"cut: tetrahedron {bad} was already removed")
        remove_blocks(self.vertex_tensors, self.edge_tensors, self.tets, self.tet_edges, self.ke, which,
                      LOCAL_EDGES, self.valence, alive)  # fmt: skip
        self.generation += 1
        return which

    def relabel(self, which, new_tets: np.ndarray, n_vertices: int) -> None:
        """Give tetrahedra ``which`` (K,) int the vertices ``new_tets`` (K, 4) int64, on a mesh of
        ``n_vertices`` >= N vertices (new ones at the end): a slit, which gives the tetrahedra on one side
        copies of the vertices they shared with the other, or a suture, which joins such copies back.
        The new vertices sit where the old ones did, so each tetrahedron's blocks ``ke`` stay; only the
        sums move: its blocks leave the old vertices and edges and join the new ones (Cotin et al.
        2000's local update). An edge that did not exist is added (the edge list is laid out again,
        O(E) copies; no block is recomputed); one left with no tetrahedron keeps a zero tensor."""
        which = np.asarray(which, dtype=np.int64)
        if np.any(~self.alive[which]):
            bad = int(which[~self.alive[which]][0])
            raise InputError(f"relabel: tetrahedron {bad} was removed by a cut")
        self._scatter(which, -1.0)
        if n_vertices > self.n_vertices:
            grown = np.zeros((n_vertices, 3, 3))
            grown[: self.n_vertices] = self.vertex_tensors
            self.vertex_tensors, self.n_vertices = grown, n_vertices
        self.tets = self.tets.copy()  # a model before the change keeps its own tets
        self.tets[which] = new_tets
        pairs = np.sort(self.tets[which][:, LOCAL_EDGES].reshape(-1, 2), axis=1)
        missing = edge_index(self.edges, self.n_vertices, pairs) < 0
        if missing.any():
            edges = np.unique(np.concatenate([self.edges, pairs[missing]]), axis=0)
            tensors = np.zeros((len(edges), 3, 3))
            tensors[edge_index(edges, self.n_vertices, self.edges)] = self.edge_tensors
            self.edges, self.edge_tensors = edges, tensors
            self.tet_edges = edge_index(self.edges, self.n_vertices, self.tets[:, LOCAL_EDGES].reshape(-1, 2))
            self.tet_edges = self.tet_edges.reshape(-1, 6)
        else:
            self.tet_edges[which] = edge_index(self.edges, self.n_vertices, pairs).reshape(-1, 6)
        self._scatter(which, +1.0)
        self._valence = None
        self.generation += 1

    def truncate(self, n_vertices: int) -> None:
        """Drop the vertices from ``n_vertices`` on, which no tetrahedron (alive or cut) may use: a suture
        that joined a slit's copies back gives the mesh its old size."""
        if self.tets.size and self.tets.max() >= n_vertices:
            raise InputError(f"truncate: a tetrahedron still uses vertex {int(self.tets.max())} >= {n_vertices}")
        keep = self.edges[:, 1] < n_vertices
        self.edges, self.edge_tensors = self.edges[keep], self.edge_tensors[keep]
        self.vertex_tensors, self.n_vertices = self.vertex_tensors[:n_vertices].copy(), n_vertices
        self.tet_edges = edge_index(self.edges, n_vertices, self.tets[:, LOCAL_EDGES].reshape(-1, 2)).reshape(-1, 6)
        self._valence = None
        self.generation += 1

    @property
    def valence(self) -> np.ndarray:
        """(N,) int64: how many alive tetrahedra use each vertex, kept by ``remove`` (a cut finds the
        vertices it leaves with none among its own, without reading the mesh); counted again after a
        relabel or truncate."""
        if getattr(self, "_valence", None) is None or len(self._valence) != self.n_vertices:
            self._valence = np.bincount(self.tets[self.alive].ravel(), minlength=self.n_vertices)
        return self._valence

    @property
    def alive(self) -> np.ndarray:
        """(M,) bool: which tetrahedra are still in the mesh."""
        if not hasattr(self, "_alive"):
            self._alive = np.ones(len(self.tets), dtype=bool)
        return self._alive

    def matrix(self) -> sp.csr_matrix:
        """The assembled stiffness K (3N, 3N) as scipy CSR, N/m (dof 3 i + c)."""
        n = self.n_vertices
        i = np.concatenate([np.arange(n), self.edges[:, 0], self.edges[:, 1]])
        j = np.concatenate([np.arange(n), self.edges[:, 1], self.edges[:, 0]])
        blocks = np.concatenate([self.vertex_tensors, self.edge_tensors, self.edge_tensors.transpose(0, 2, 1)])
        return assemble_blocks(i, j, blocks, n)

    def kernel_data(self, dtype=np.float64) -> TensorData:
        """The tuple the force kernel ``linear_tm_force`` takes, laid out for one forward pass:
        vertex tensors (N,3,3), cols (E,) int64 (the larger end j of each edge), edge tensors (E,3,3),
        and row_start (N+1,) int64: the edges (i, j > i) of vertex i are row_start[i]:row_start[i+1]
        (``edges`` is sorted by i). Contiguous arrays; no stride-2 index reads in the hot loop. The
        tensors are this object's own arrays in float64 (what cutting updates in place is what the
        kernel reads), or rounded copies in float32 (a float32 model, which cannot be cut)."""
        row_start = np.searchsorted(self.edges[:, 0], np.arange(self.n_vertices + 1)).astype(np.int64)
        return TensorData(
            np.ascontiguousarray(self.vertex_tensors, dtype=dtype),
            np.ascontiguousarray(self.edges[:, 1]),
            np.ascontiguousarray(self.edge_tensors, dtype=dtype),
            row_start,
        )


@nb.njit(inline="always", **_HOT)
def linear_rows(cols, et, row_start, lo, hi, u, f):
    """linear_tm_force's pass over the vertex rows lo .. hi - 1, adding into f: vertex i gathers
    -sum_j T_ij (u_j - u_i) over its edges (i, j > i) in registers and scatters T_ij^T (u_j - u_i)
    to each j; f_i is written once. Each edge tensor is loaded once into registers.

    cols (E,) int64, row_start (N + 1,) int64 as in TensorData; et (9 E,) the edge tensors, u (3 N,)
    m and f (3 N,) N flat (row-major views of the (E, 3, 3) and (N, 3) arrays), read with unsigned
    offsets (blocks.U1 ...: 20% faster than 2-D signed indexing, liver-x10 503 against 405 us, same
    bits)."""
    for i in range(lo, hi):
        bi = U3 * np.uint64(i)
        ui0, ui1, ui2 = u[bi], u[bi + U1], u[bi + U2]
        a0, a1, a2 = f[bi], f[bi + U1], f[bi + U2]
        for e in range(np.uint64(row_start[i]), np.uint64(row_start[i + 1])):
            bj = U3 * np.uint64(cols[e])
            be = U9 * e
            t00, t01, t02 = et[be], et[be + U1], et[be + U2]
            t10, t11, t12 = et[be + U3], et[be + U4], et[be + U5]
            t20, t21, t22 = et[be + U6], et[be + U7], et[be + U8]
            d0, d1, d2 = u[bj] - ui0, u[bj + U1] - ui1, u[bj + U2] - ui2
            a0 -= t00 * d0 + t01 * d1 + t02 * d2
            a1 -= t10 * d0 + t11 * d1 + t12 * d2
            a2 -= t20 * d0 + t21 * d1 + t22 * d2
            f[bj] += t00 * d0 + t10 * d1 + t20 * d2
            f[bj + U1] += t01 * d0 + t11 * d1 + t21 * d2
            f[bj + U2] += t02 * d0 + t12 * d1 + t22 * d2
        f[bi] = a0
        f[bi + U1] = a1
        f[bi + U2] = a2


@nb.njit(**_HOT)
def linear_tm_force(data, scratch, u, f):
    """f = -K u from the edge tensors in difference form (the module's docstring), in one pass over the
    vertices (linear_rows).

    data: TensorData (its vertex tensors are not read).   scratch: model.NO_SCRATCH (unused).
    u: (N, 3) displacement, m.   f: (N, 3) output force, N (overwritten). u, f and the tensors all
    float64, or all float32 (a float32 model: the kernel then computes in float32).
    """
    f1 = f.reshape(-1)
    f1[:] = 0.0
    linear_rows(data.cols, data.edge_tensors.reshape(-1), data.row_start, 0, u.shape[0], u.reshape(-1), f1)


@nb.njit(**_JIT)
def linear_tm_energy(data, u):
    """Elastic energy u^T K u / 2, J, for the same data and u as linear_tm_force."""
    vt, cols, et, row_start = data
    w = 0.0
    for i in range(u.shape[0]):
        for r in range(3):
            for c in range(3):
                w += 0.5 * u[i, r] * vt[i, r, c] * u[i, c]
        for e in range(row_start[i], row_start[i + 1]):
            j = cols[e]
            for r in range(3):
                for c in range(3):
                    w += u[i, r] * et[e, r, c] * u[j, c]
    return w
