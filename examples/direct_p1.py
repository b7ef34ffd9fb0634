"""An engine no one in the project wrote against: linear elasticity, P1, assembled and solved directly with
numpy and scipy from an exported scene (``tissuebench export``), nothing of the project imported.

    python direct_p1.py SCENE_DIR RESULT.npz

Static scenes only: K u = f with the held components at zero and the tools' components at their final
prescribed displacement. K is the standard P1 stiffness of an isotropic linear material per tetrahedron,
K_ab = V (lambda g_a g_b^T + mu g_b g_a^T + mu (g_a . g_b) I), g the gradients of the barycentric
coordinates (Zienkiewicz & Taylor, The Finite Element Method, vol. 1, ch. 6).
"""

import json
import sys
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def stiffness(points, tets, lam, mu):
    x = points[tets]  # (M, 4, 3)
    d = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)  # columns: edges
    inv = np.linalg.inv(d)  # rows: gradients of barycentric coordinates 1..3
    g = np.concatenate([-inv.sum(axis=1, keepdims=True), inv], axis=1)  # (M, 4, 3)
    vol = np.abs(np.linalg.det(d)) / 6.0
    rows, cols, vals = [], [], []
    eye = np.eye(3)
    for a in range(4):
        for b in range(4):
            ga, gb = g[:, a], g[:, b]
            block = (
                lam[:, None, None] * ga[:, :, None] * gb[:, None, :]
                + mu[:, None, None] * gb[:, :, None] * ga[:, None, :]
                + (mu * np.einsum("ij,ij->i", ga, gb))[:, None, None] * eye
            ) * vol[:, None, None]
            for i in range(3):
                for j in range(3):
                    rows.append(3 * tets[:, a] + i)
                    cols.append(3 * tets[:, b] + j)
                    vals.append(block[:, i, j])
    n = 3 * len(points)
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


def main(scene_dir: str, result: str) -> None:
    scene = json.loads((Path(scene_dir) / "scene.json").read_text())
    if scene["time"]["mode"] != "static":
        sys.exit("direct_p1: static scenes only")
    z = np.load(Path(scene_dir) / "arrays.npz")
    mats = scene["materials"]
    index = z["material_index"]
    lam = np.array([m["lambda_pa"] for m in mats])[index]
    mu = np.array([m["mu_pa"] for m in mats])[index]
    t0 = time.perf_counter()
    K = stiffness(z["points"], z["tets"], lam, mu)
    u = np.zeros(K.shape[0])
    for v, mask, d in zip(z["tool_vertex"], z["tool_mask"], z["tool_displacement"][-1], strict=True):
        for c in range(3):
            if mask[c]:
                u[3 * v + c] = d[c]
    free = np.flatnonzero(z["free"].reshape(-1) != 0.0)
    rhs = z["external_force"].reshape(-1) - K @ u
    u[free] = spla.spsolve(K[free][:, free].tocsc(), rhs[free])
    np.savez(result, displacement=u.reshape(-1, 3), step_us=(time.perf_counter() - t0) * 1e6)


if __name__ == "__main__":
    main(*sys.argv[1:3])
