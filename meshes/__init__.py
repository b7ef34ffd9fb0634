"""tissuebench meshes: gmsh generators, meshio I/O, quality checks, region selectors, stored meshes."""

from .generators import GENERATORS, box, cylinder, generate, liver, tube
from .io import read_mesh, write_mesh
from .store import STORED, get_mesh, stored_mesh
from .tetmesh import InvalidMeshError, TetMesh, structured_box

__all__ = [
    "GENERATORS",
    "STORED",
    "InvalidMeshError",
    "TetMesh",
    "box",
    "cylinder",
    "generate",
    "get_mesh",
    "liver",
    "read_mesh",
    "stored_mesh",
    "structured_box",
    "tube",
    "write_mesh",
]
