"""Topology changes of a linear tensor-mass model besides cutting: slitting and suturing.

``realtime.models.linear_tm.cut`` removes tetrahedra (Cotin et al. 2000). A scalpel that leaves no gap is a
*slit*: the mesh separates along interior triangles, each vertex on them split into one copy per side,
so that the tetrahedra on either side no longer share it. *Suturing* is its inverse: joining two
vertex sets that sit at the same place (the two lips of a slit) back into one. Both are local
tensor updates (``TensorMass.relabel``): the tetrahedra whose vertices change move their stiffness
blocks from the old vertices and edges to the new ones; no element stiffness is recomputed, since a
copy sits where its original is. The lumped masses move with the tetrahedra.

Vertex indices stay valid: a slit appends its copies after the mesh's vertices; a suture leaves a
joined vertex unused and held (as a cut leaves an orphan), except that the copies a slit appended are
dropped again when a suture leaves them unused at the end, so that slitting and suturing back returns
the model's own vertex set. The model returned is a new Model; the one before the change shares the
updated tensors, so every integrator refuses to step it (``Model.check_current``).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .contact import below
from .errors import InputError, index_array
from .geometry import TET_FACES, signed_volumes
from .material import Material
from .model import Deferred, Loading, Model, check_float64
from .threaded import linear_tm_kernel

#: Two vertices are joined only where they coincide: within this fraction of the mesh's size.
COINCIDE = 1e-9


def _tensors(model: Model, what: str):
    tm = model.extra.get("tensors")
    if not model.extra.get("cuttable") or tm is None:
        raise InputError(f"{what}: {model.name} does not support topology changes (ModelSpec.cuttable)")
    model.check_current()
    check_float64(model, what)
    return tm


def _masses(model: Model, tm, which: np.ndarray, old: np.ndarray, n: int) -> np.ndarray:
    """The lumped masses (n,) kg after tetrahedra ``which`` moved from vertices ``old`` (K, 4) to
    ``tm.tets[which]``: each one's rho V / 4 leaves the old vertices and joins the new."""
    mass = np.zeros(n)
    mass[: min(n, model.n_vertices)] = model.mass[: min(n, model.n_vertices)]
    share = np.repeat(tm.materials.per_tet("density")[which] * np.abs(signed_volumes(model.points, old)) / 4.0, 4)
    np.subtract.at(mass, old.ravel(), share)
    np.add.at(mass, tm.tets[which].ravel(), share)
    return mass


def changed_model(model: Model, tm, points, mass, loading: Loading, data=None, orphans=None) -> Model:
    """The successor of ``model`` after its TensorMass ``tm`` changed (a cut, slit or suture): its alive
    tetrahedra, masses (N,) kg and loading on ``points`` (N, 3) m, a vertex left with no tetrahedron
    held and given a unit mass (never used: it does not move; it keeps 1/m finite). ``data``: the
    kernel's, if the change kept its arrays (a cut); else laid out again from ``tm`` (for as many
    threads as the model's). ``orphans`` (K,) int: the vertices left with no tetrahedron, where the change knows
    them (a cut: among its own); then nothing the size of the mesh is read or checked, the loading is
    kept where no vertex was orphaned, and the tetrahedra and the material are made when first read
    (``Deferred``), from the alive set as it is now."""
    known = orphans is not None
    if not known:
        unused = np.ones(len(points), dtype=bool)
        unused[tm.tets[tm.alive].ravel()] = False
        orphans = np.flatnonzero(unused)
    if len(orphans):
        free = loading.free.copy()
        free[orphans] = 0.0
        loading = Loading(**{**loading.__dict__, "free": free})
        mass = mass.copy()
        mass[orphans] = 1.0
    if not known:
        loading.check(len(points))
    extra = {**model.extra, "generation": tm.generation}
    alive = tm.alive.copy()  # the next cut changes tm.alive in place
    given = model.__dict__["material"]  # as given: reading a Deferred would make it
    material = given if isinstance(given, Material) else Deferred(lambda: tm.materials.subset(alive))
    kernel = {}
    if data is None:
        force, energy, data, scratch = linear_tm_kernel(tm, model.extra.get("threads", 1))
        kernel = {"force_kernel": force, "energy_kernel": energy, "new_scratch": scratch}
    tets = tm.tets
    return Model(
        **{
            **model.__dict__,
            "material": material,
            "points": points,
            "tets": Deferred(lambda: tets[alive]),
            "mass": mass,
            "loading": loading,
            "data": data,
            "extra": extra,
            **kernel,
        }
    )


def slit_tets(tets: np.ndarray, n: int, faces, what: str = "slit") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The vertex splitting of a slit, on a mesh's tetrahedra ``tets`` (M, 4) int64 over ``n`` vertices,
    along interior triangles ``faces`` (F, 3) int (vertex indices, any order), each shared by two
    tetrahedra (InputError naming the first that is not, ``what`` leading the message).

    Around each vertex of the slit, the tetrahedra that still connect through faces off the slit form
    one side; each side but the first gets a copy of the vertex, numbered n, n + 1, ... in order (a
    vertex where the slit ends inside the body has one side and stays whole). Returns the positions
    (C,) int64 of the tetrahedra whose vertices changed, their new rows (C, 4) int64, and the pairs
    (K, 2) int64 (original, copy)."""
    faces = index_array(f"{what}: face", faces, n, width=3)
    m = len(tets)
    tet_faces = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)  # (4 M, 3)
    key = (tet_faces[:, 0] * n + tet_faces[:, 1]) * n + tet_faces[:, 2]
    slit_keys = set()
    for f in np.sort(faces, axis=1):
        k = (f[0] * n + f[1]) * n + f[2]
        if np.count_nonzero(key == k) != 2:
            raise InputError(
                f"{what}: face {f.tolist()} is not an interior triangle of the mesh (shared by two tetrahedra)"
            )
        slit_keys.add(int(k))
    slit_list = np.array(sorted(slit_keys), dtype=np.int64)
    owner = np.repeat(np.arange(m), 4)
    new_tets = {}
    copies = []
    for v in np.unique(faces):
        around = np.flatnonzero(np.any(tets == v, axis=1))
        local = np.full(m, -1, dtype=np.int64)
        local[around] = np.arange(len(around))
        # the faces through v of the tetrahedra around it, paired where two tetrahedra share one off the slit
        mine = (local[owner] >= 0) & np.any(tet_faces == v, axis=1)
        fk, ft = key[mine], owner[mine]
        order = np.argsort(fk, kind="stable")
        fk, ft = fk[order], ft[order]
        same = (fk[1:] == fk[:-1]) & ~np.isin(fk[1:], slit_list)
        a, b = local[ft[:-1][same]], local[ft[1:][same]]
        graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(around), len(around)))
        count, side = connected_components(graph, directed=False)
        for k in range(1, count):
            copy = n + len(copies)
            copies.append((int(v), copy))
            for t in around[side == k]:
                row = new_tets.setdefault(int(t), tets[t].copy())
                row[row == v] = copy
    changed = np.array(sorted(new_tets), dtype=np.int64)
    rows = np.array([new_tets[int(t)] for t in changed], dtype=np.int64).reshape(-1, 4)
    return changed, rows, np.array(copies, dtype=np.int64).reshape(-1, 2)


def slit(model: Model, faces) -> tuple[Model, np.ndarray]:
    """Separate a linear tensor-mass model along interior triangles ``faces`` (F, 3) int (vertex
    indices, any order), each shared by two tetrahedra of the model: its vertices split as
    ``slit_tets`` splits them, the copies appended after the mesh's vertices. The copies take their
    share of the vertex's external force by mass (exact for gravity) and its constraints; tools keep
    driving the originals. Returns the new model and the pairs (K, 2) int64 (original, copy), which
    ``suture`` takes to join them back.
    """
    tm = _tensors(model, "slit")
    n = model.n_vertices
    alive = np.flatnonzero(tm.alive)
    changed, rows, pairs = slit_tets(tm.tets[alive], n, faces, "slit")
    if not len(pairs):
        return model, pairs
    which = alive[changed]
    old = tm.tets[which].copy()
    n_new = n + len(pairs)
    tm.relabel(which, rows, n_new)
    points = np.concatenate([model.points, model.points[pairs[:, 0]]])
    mass = _masses(model, tm, which, old, n_new)
    lo = model.loading
    fext = np.concatenate([lo.external_force, np.zeros((len(pairs), 3))])
    for orig in np.unique(pairs[:, 0]):  # the force follows the mass, among the original and its copies
        group = np.concatenate([[orig], pairs[pairs[:, 0] == orig, 1]])
        total = fext[orig].copy()
        fext[group] = total[None, :] * (mass[group] / mass[group].sum())[:, None]
    free = np.concatenate([lo.free, lo.free[pairs[:, 0]]])
    loading = Loading(**{**lo.__dict__, "free": free, "external_force": fext})
    return changed_model(model, tm, points, mass, loading), pairs


def suture(model: Model, pairs) -> Model:
    """Join vertex pairs (K, 2) int of a linear tensor-mass model: every tetrahedron using the second
    vertex of a pair uses the first instead. The two must coincide (rest positions within COINCIDE of
    the mesh's size), as the lips of a slit do; the second may not be a tool's. It keeps no
    tetrahedron, its mass and external force go to the first, and it is left unused and held, or
    dropped if it and every vertex after it are now unused copies a slit appended.
    """
    tm = _tensors(model, "suture")
    n = model.n_vertices
    pairs = index_array("suture: pair", pairs, n, width=2)
    size = float(np.ptp(model.points, axis=0).max())
    gap = np.linalg.norm(model.points[pairs[:, 0]] - model.points[pairs[:, 1]], axis=1)
    if np.any(gap > COINCIDE * size) or np.any(pairs[:, 0] == pairs[:, 1]):
        k = int(np.argmax(gap)) if np.any(gap > COINCIDE * size) else int(np.argmax(pairs[:, 0] == pairs[:, 1]))
        raise InputError(
            f"suture: vertices {pairs[k].tolist()} are {gap[k]:.3g} m apart; a suture joins two copies of one "
            "place (distinct vertices at the same rest position)"
        )
    driven = np.isin(pairs[:, 1], model.loading.tool_vertex)
    if driven.any():
        raise InputError(f"suture: vertex {int(pairs[driven][0, 1])} is driven by a tool; put it first in its pair")
    target = np.arange(n)
    target[pairs[:, 1]] = pairs[:, 0]
    target = target[target]  # a chain a <- b <- c joins c to a
    alive = np.flatnonzero(tm.alive)
    which = alive[np.any(np.isin(tm.tets[alive], pairs[:, 1]), axis=1)]
    new = target[tm.tets[which]]
    flat = np.sort(new, axis=1)
    if np.any(flat[:, 1:] == flat[:, :-1]):
        t = int(which[np.argmax(np.any(flat[:, 1:] == flat[:, :-1], axis=1))])
        raise InputError(
            f"suture: tetrahedron {t} would hold one vertex twice; a suture joins vertices of different tetrahedra"
        )
    old = tm.tets[which].copy()
    tm.relabel(which, new, n)
    mass = _masses(model, tm, which, old, n)
    lo = model.loading
    fext = lo.external_force.copy()
    np.add.at(fext, target[pairs[:, 1]], fext[pairs[:, 1]])
    fext[pairs[:, 1]] = 0.0
    loading = Loading(**{**lo.__dict__, "external_force": fext})
    points = model.points
    # drop the trailing copies this suture left unused, so that a slit sutured back has its old size
    used = np.zeros(n, dtype=bool)
    used[tm.tets.ravel()] = True
    joined = np.zeros(n, dtype=bool)
    joined[pairs[:, 1]] = True
    keep = n
    while keep > 0 and joined[keep - 1] and not used[keep - 1]:
        keep -= 1
    if keep < n:
        tm.truncate(keep)
        points, mass = points[:keep], mass[:keep]
        loading = Loading(
            **{
                **loading.__dict__,
                "free": loading.free[:keep],
                "external_force": loading.external_force[:keep],
                "contacts": below(loading.contacts, keep),
            }
        )
    return changed_model(model, tm, points, mass, loading)
