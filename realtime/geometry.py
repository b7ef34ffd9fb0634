"""Geometry of linear tetrahedra: volumes, shape-function gradients, edges, boundary faces.

Arrays:
    points: (N, 3) float64, m.
    tets:   (M, 4) integer vertex indices, positively oriented
            (det[x1 - x0, x2 - x0, x3 - x0] > 0).
"""

from __future__ import annotations

import numpy as np

from .errors import InputError

#: A tetrahedron whose volume is below this fraction of (mean edge length)^3 / (6 sqrt 2) is
#: degenerate: a regular tetrahedron's volume is L^3 / (6 sqrt 2), and 1e-8 of that is far below any
#: element a mesher produces on purpose yet far above round-off (~1e-16).
DEGENERATE_RATIO = 1e-8


class InvalidMeshError(InputError):
    """A mesh that cannot be simulated; the message names the element and the value."""


def edge_matrices(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Edge vectors D[e] = [x1 - x0, x2 - x0, x3 - x0] as columns, (M, 3, 3) float64, m."""
    x = points[tets]
    return np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)


def signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes det(D)/6, (M,) float64, m^3; positive for positively oriented tetrahedra."""
    return np.linalg.det(edge_matrices(points, tets)) / 6.0


def check_tets(points: np.ndarray, tets: np.ndarray, where: str = "mesh") -> np.ndarray:
    """Validate a tetrahedral mesh and return its volumes (M,) float64, m^3.

    Raises InvalidMeshError naming the first bad element: index out of range, repeated vertex,
    non-finite coordinate, inverted (negative volume) or degenerate (near-zero volume).
    """
    points = np.asarray(points)
    tets = np.asarray(tets)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidMeshError(f"{where}: points must have shape (N, 3), got {points.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise InvalidMeshError(f"{where}: tets must have shape (M, 4), got {tets.shape}")
    if len(tets) == 0:
        raise InvalidMeshError(f"{where}: no tetrahedra")
    if not np.all(np.isfinite(points)):
        bad = int(np.argwhere(~np.isfinite(points))[0, 0])
        raise InvalidMeshError(f"{where}: vertex {bad} has a non-finite coordinate {points[bad]}")
    if tets.min() < 0 or tets.max() >= len(points):
        bad = int(np.argwhere((tets < 0) | (tets >= len(points)))[0, 0])
        raise InvalidMeshError(
            f"{where}: tetrahedron {bad} {tets[bad].tolist()} refers to a vertex outside 0..{len(points) - 1}"
        )
    srt = np.sort(tets, axis=1)
    repeated = np.any(srt[:, 1:] == srt[:, :-1], axis=1)
    if np.any(repeated):
        bad = int(np.argmax(repeated))
        raise InvalidMeshError(f"{where}: tetrahedron {bad} {tets[bad].tolist()} repeats a vertex")
    vol = signed_volumes(points, tets)
    x = points[tets]
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    mean_edge = np.mean([np.linalg.norm(x[:, a] - x[:, b], axis=1) for a, b in pairs], axis=0)
    scale = mean_edge**3 / (6.0 * np.sqrt(2.0))
    degenerate = np.abs(vol) <= DEGENERATE_RATIO * scale
    if np.any(degenerate):
        bad = int(np.argmax(degenerate))
        more = int(degenerate.sum()) - 1
        why = (
            f"(volume {vol[bad]:.3e} m^3 for edges of {mean_edge[bad]:.3e} m: {abs(vol[bad]) / scale[bad]:.1e} "
            f"of a regular tetrahedron's, below {DEGENERATE_RATIO:g})"
            if scale[bad] > 0.0
            else f"(its four vertices are one point, {x[bad, 0].tolist()})"
        )
        raise InvalidMeshError(
            f"{where}: tetrahedron {bad} {tets[bad].tolist()} is degenerate {why}"
            + (f"; {more} more like it" if more else "")
        )
    if np.any(vol < 0.0):
        bad = int(np.argmax(vol < 0.0))
        raise InvalidMeshError(
            f"{where}: tetrahedron {bad} {tets[bad].tolist()} is inverted (volume {vol[bad]:.3e} m^3)"
        )
    return vol


def orient_positive(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Tets (M, 4) with the last two vertices swapped wherever the volume is negative."""
    tets = np.array(tets, dtype=np.int64, copy=True)
    neg = signed_volumes(points, tets) < 0.0
    tets[neg, 2], tets[neg, 3] = tets[neg, 3].copy(), tets[neg, 2].copy()
    return tets


def shape_gradients(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of the four barycentric shape functions and the volumes.

    Returns:
        grads: (M, 4, 3) float64, 1/m; grads[e, a] = grad N_a on tetrahedron e, sum over a is zero.
        vol:   (M,) float64, m^3.
    """
    d = edge_matrices(points, tets)
    inv = np.linalg.inv(d)  # rows of D^-1 are grad N_1..N_3
    grads = np.empty((len(tets), 4, 3))
    grads[:, 1:, :] = inv
    grads[:, 0, :] = -inv.sum(axis=1)
    return grads, np.linalg.det(d) / 6.0


def unique_edges(tets: np.ndarray) -> np.ndarray:
    """The mesh's edges (E, 2) int64 with edges[:, 0] < edges[:, 1], sorted lexicographically."""
    pairs = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
    e = np.sort(np.asarray(tets, dtype=np.int64)[:, pairs].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0)


#: Local faces of a tetrahedron, each ordered so that its normal (right-hand rule) points outwards
#: for a positively oriented tetrahedron.
TET_FACES = np.array([(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)])


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles (F, 3) int64 with outward normals: faces belonging to one tetrahedron."""
    faces = np.asarray(tets, dtype=np.int64)[:, TET_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1]


def face_areas(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Areas of triangles (F,) float64, m^2."""
    x = points[faces]
    return 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)


def lumped_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Volume attached to each vertex, a quarter of each tetrahedron around it, (N,) float64, m^3."""
    vol = np.abs(signed_volumes(points, tets))
    out = np.zeros(len(points))
    np.add.at(out, np.asarray(tets).ravel(), np.repeat(vol / 4.0, 4))
    return out


def lumped_areas(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Boundary area attached to each vertex, a third of each triangle around it, (N,), m^2."""
    out = np.zeros(len(points))
    if len(faces):
        np.add.at(out, np.asarray(faces).ravel(), np.repeat(face_areas(points, faces) / 3.0, 3))
    return out


def min_altitudes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Smallest altitude of each tetrahedron (M,) float64, m: 3 V / (largest face area).

    This is the length L_min of the element estimate of the critical time step L_min / c_p.
    """
    vol = np.abs(signed_volumes(points, tets))
    faces = np.asarray(tets)[:, TET_FACES]  # (M, 4, 3)
    x = points[faces]
    areas = 0.5 * np.linalg.norm(np.cross(x[:, :, 1] - x[:, :, 0], x[:, :, 2] - x[:, :, 0]), axis=2)
    return 3.0 * vol / areas.max(axis=1)


def morton_order(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Permutation (M,) int64 that sorts tetrahedra along the Z-order (Morton) curve of their centroids
    on a 1024^3 grid: tetrahedra close in space come out close in the order, so a block of them
    touches few vertices (cache reuse) and a local deformation touches few blocks."""
    c = points[tets].mean(axis=1)
    lo, span = c.min(axis=0), np.maximum(np.ptp(c, axis=0), np.finfo(float).tiny)
    q = np.minimum((c - lo) / span * 1024, 1023).astype(np.int64)
    code = np.zeros(len(q), dtype=np.int64)
    for bit in range(10):
        for d in range(3):
            code |= ((q[:, d] >> bit) & 1) << (3 * bit + d)
    return np.argsort(code, kind="stable")


def spatial_numbering(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A numbering of a mesh along the body: (vertex_order (N,), tet_order (M,)) int64, the old index of
    each new vertex and tetrahedron. The tetrahedra follow the Morton curve of their centroids
    (morton_order, the order the element kernels' blocks take). The vertices follow the order in which
    they first appear in those tetrahedra, in three groups: those only the first half of the curve
    touches, those both halves touch (the interface), those only the second half touches; vertices of
    no tetrahedron last, in their old order.

    The force kernels gather u and scatter f by vertex number, and a threaded kernel's threads each
    take a compact piece of the body (two threads: the two halves of the curve); numbered this way, a
    piece's vertices are a nearly contiguous range, so the gathers reuse cache lines and the two cores
    share few of them (on liver-x10, the cache lines of f written by both threads of a two-thread
    stvk-tm fell from 77% to 17%, about the share of the vertices both pieces hold). With the
    interface between the two halves' own vertices, each thread writes forces in one range of the
    vertices and the two ranges overlap on the interface alone (threaded.force_spans), which is all
    the threads must add and all they read of the other core's forces. A mesh file's own numbering
    (gmsh's) follows the mesher, not the body."""
    tet_order = morton_order(points, tets)
    t = np.asarray(tets, dtype=np.int64)[tet_order]
    seq = t.ravel()
    used, first = np.unique(seq, return_index=True)
    by_first = used[np.argsort(first)]
    half = -(-len(t) // 2)
    in_first, in_second = np.zeros(len(points), bool), np.zeros(len(points), bool)
    in_first[t[:half].ravel()] = True
    in_second[t[half:].ravel()] = True
    group = np.where(in_first & in_second, 1, np.where(in_first, 0, 2))[by_first]
    unused = np.setdiff1d(np.arange(len(points)), used)
    return np.concatenate([by_first[np.argsort(group, kind="stable")], unused]).astype(np.int64), tet_order


def inverse_order(order: np.ndarray) -> np.ndarray:
    """(K,) int64: the new index of each old item, for ``order`` (K,) int64 the old index of each new one."""
    new = np.empty(len(order), dtype=np.int64)
    new[order] = np.arange(len(order))
    return new


def renumbered(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh (points (N, 3) m, tets (M, 4) int) renumbered along the body (spatial_numbering): new
    points (N, 3), new tets (M, 4) int64 (the same tetrahedra, corners in the same order, so the same
    orientation) and vertex_order (N,) int64, the old index of each new vertex. A state in the old
    numbering maps to the new one by ``u[vertex_order]``, and back by ``u_old[vertex_order] = u``.
    Build the model on the new mesh once, before a simulation: it steps faster, more so on threads."""
    vertex_order, tet_order = spatial_numbering(points, tets)
    return np.asarray(points)[vertex_order], inverse_order(vertex_order)[np.asarray(tets)[tet_order]], vertex_order


def red_refinement(points: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each tetrahedron cut into eight (red refinement: four corner tetrahedra and the inner octahedron
    split along its shortest diagonal, the best-shaped children).

    points (N, 3) float64 m, tets (M, 4) int64. Returns the fine points (N + E, 3): the N vertices keep
    their indices and the midpoints of the E edges of ``unique_edges(tets)`` follow in that order; and
    the fine tets (8 M, 4) int64, positively oriented, child j of coarse tetrahedron j mod M."""
    e = unique_edges(tets)
    n = len(points)
    t = np.asarray(tets, dtype=np.int64)
    pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    keys = e[:, 0] * n + e[:, 1]
    m = np.empty((len(t), 6), dtype=np.int64)
    for j, (a, b) in enumerate(pairs):
        lo, hi = np.minimum(t[:, a], t[:, b]), np.maximum(t[:, a], t[:, b])
        m[:, j] = n + np.searchsorted(keys, lo * n + hi)
    x0, x1, x2, x3 = t.T
    m01, m02, m03, m12, m13, m23 = m.T
    fine = np.vstack([points, 0.5 * (points[e[:, 0]] + points[e[:, 1]])])
    # the inner octahedron: four tetrahedra around one of its three diagonals, each diagonal with the
    # cycle of the four other midpoints around it
    octahedra = {
        (0, 5): (1, 2, 4, 3),  # m01-m23 around m02, m03, m13, m12
        (1, 4): (0, 2, 5, 3),  # m02-m13 around m01, m03, m23, m12
        (2, 3): (0, 1, 5, 4),  # m03-m12 around m01, m02, m23, m13
    }
    length = np.stack([np.linalg.norm(fine[m[:, a]] - fine[m[:, b]], axis=1) for a, b in octahedra], axis=1)
    choice = np.argmin(length, axis=1)
    inner = np.zeros((4, len(t), 4), dtype=np.int64)
    for k, ((a, b), ring) in enumerate(octahedra.items()):
        sel = choice == k
        for i in range(4):
            inner[i, sel] = np.stack([m[sel, a], m[sel, b], m[sel, ring[i]], m[sel, ring[(i + 1) % 4]]], axis=1)
    corners = [(x0, m01, m02, m03), (m01, x1, m12, m13), (m02, m12, x2, m23), (m03, m13, m23, x3)]
    children = np.concatenate([np.stack(c, axis=1) for c in corners] + list(inner))
    return fine, orient_positive(fine, children)
