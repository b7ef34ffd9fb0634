"""Stored meshes: the meshes of the built-in scenes, tests and gates, kept with their hash.

``get_mesh(generator, params)`` returns the stored mesh when one was stored for exactly these
parameters (and checks its hash), and otherwise generates it. ``python -m meshes.store`` regenerates
every stored mesh and rewrites ``data/manifest.json``; a test regenerates them and compares hashes,
so a gmsh upgrade that changes a mesh is caught instead of silently moving every baseline.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .generators import generate
from .io import atomic_savez
from .tetmesh import InvalidMeshError, TetMesh

DATA = Path(__file__).parent / "data"
MANIFEST = DATA / "manifest.json"

#: name -> (generator, parameters). What the built-in scenes and the benchmarks use.
STORED = {
    "beam": ("box", {"size": [0.1, 0.02, 0.02], "h": 0.005}),
    "beam-slender": ("box", {"size": [0.2, 0.02, 0.02], "h": 0.005}),
    "cylinder": ("cylinder", {"radius": 0.01, "length": 0.1, "h": 0.004}),
    "tube": ("tube", {"inner_radius": 0.006, "outer_radius": 0.01, "length": 0.1, "h": 0.003}),
    "liver": ("liver", {"scale": 1.0, "h": 0.0102}),
    "liver-x10": ("liver", {"scale": 1.0, "h": 0.00473}),
}


def params_key(generator: str, params: dict) -> str:
    """Canonical text of a generator call, the key of the manifest."""

    def clean(v):
        if isinstance(v, dict):  # a graded box's fine region
            return {k: clean(x) for k, x in v.items()}
        return list(map(float, v)) if isinstance(v, (list, tuple)) else float(v)

    return json.dumps({"generator": generator, **{k: clean(v) for k, v in params.items()}}, sort_keys=True)


def _manifest() -> dict:
    return json.loads(MANIFEST.read_text()) if MANIFEST.exists() else {}


def save_npz(mesh: TetMesh, path: Path) -> None:
    """Exact binary copy of a mesh with its tags, written atomically."""
    arrays = {"points": mesh.points, "tets": mesh.tets}
    arrays.update({f"vtag:{k}": v for k, v in mesh.vertex_tags.items()})
    arrays.update({f"ctag:{k}": v for k, v in mesh.cell_tags.items()})
    atomic_savez(path, compressed=True, **arrays)


def load_npz(path: Path, source: str = "") -> TetMesh:
    with np.load(path) as z:
        vt = {k[5:]: z[k] for k in z.files if k.startswith("vtag:")}
        ct = {k[5:]: z[k] for k in z.files if k.startswith("ctag:")}
        return TetMesh(z["points"], z["tets"], vertex_tags=vt, cell_tags=ct, source=source or str(path))


def get_mesh(generator: str, params: dict) -> TetMesh:
    """The stored mesh for this generator call if there is one (hash checked), else a new one."""
    key = params_key(generator, params)
    entry = _manifest().get(key)
    if entry is not None:
        path = DATA / entry["file"]
        mesh = load_npz(path, source=f"{path.name} ({generator} {params})")
        if mesh.sha256() != entry["sha256"]:
            raise InvalidMeshError(
                f"{path}: stored mesh hash {mesh.sha256()[:12]}... differs from the manifest's "
                f"{entry['sha256'][:12]}...; the file was changed: restore it or run python -m meshes.store"
            )
        return mesh
    return generate(generator, **params)


#: A stored mesh's name with this suffix names that mesh numbered along the body (TetMesh.renumbered):
#: the same vertices and tetrahedra in the order the real-time engine steps fastest.
RENUMBERED = "-renumbered"


def stored_names() -> list[str]:
    """Every name stored_mesh takes: STORED's, then each with RENUMBERED."""
    return sorted(STORED) + [name + RENUMBERED for name in sorted(STORED)]


def stored_mesh(name: str) -> TetMesh:
    """A stored mesh by its name in STORED, or by that name with RENUMBERED: the mesh renumbered."""
    base = name.removesuffix(RENUMBERED)
    if base != name and base in STORED:
        return stored_mesh(base).renumbered()[0]
    generator, params = STORED[name]
    return get_mesh(generator, params)


def regenerate() -> dict:
    """Generate every mesh of STORED, write it and the manifest; return the manifest."""
    import gmsh

    DATA.mkdir(exist_ok=True)
    manifest = {}
    for name, (generator, params) in STORED.items():
        mesh = generate(generator, **params)
        save_npz(mesh, DATA / f"{name}.npz")
        manifest[params_key(generator, params)] = {
            "name": name,
            "file": f"{name}.npz",
            "sha256": mesh.sha256(),
            "n_vertices": mesh.n_vertices,
            "n_tets": mesh.n_tets,
            "gmsh": gmsh.__version__,
        }
    MANIFEST.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")
    return manifest


if __name__ == "__main__":
    for entry in regenerate().values():
        print(
            f"{entry['name']:>14}  {entry['n_vertices']:>7} vertices {entry['n_tets']:>8} tets  {entry['sha256'][:16]}"
        )
