"""Experiment 1, global rotation: a rigid rotation should cost linear elasticity energy (and so ghost
forces), and cost StVK and corotational tensor-mass none."""

from __future__ import annotations

import math

import matplotlib.pyplot as plt
import numpy as np

from meshes.store import get_mesh
from realtime import Loading, Material, NotConvergedError, State, SymplecticEuler, build_model
from realtime.geometry import signed_volumes
from realtime.models import linear_tm
from verification.figures import png
from verification.progress import log
from verification.studies.seeds.common import TENSOR_MASS, Size, _finding, _volume_change


def rotation_matrix(axis, angle: float) -> np.ndarray:
    """Rodrigues' rotation (3, 3) by ``angle`` radians about the unit ``axis``."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * k @ k


def linear_rotation_energy(young: float, poisson: float, volume: float, angle: float) -> float:
    """Linear elastic energy, J, of a body of ``volume`` m^3 turned rigidly by ``angle`` radians.

    u = (R - I) X has the constant small strain eps = (cos t - 1)(I - a a^T), so tr eps = 2 (cos t - 1)
    and eps : eps = 2 (cos t - 1)^2, and W = lambda/2 (tr eps)^2 + mu eps : eps = 2 (lambda + mu)
    (1 - cos t)^2, with lambda + mu = E / (2 (1 + nu)(1 - 2 nu)) written from E and nu here, not
    taken from the engine's conversion.
    """
    return young / ((1.0 + poisson) * (1.0 - 2.0 * poisson)) * (1.0 - math.cos(angle)) ** 2 * volume


def released_rotation(mass: np.ndarray, x: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Where a damped linear body released from the affine displacement u0 = G x settles: the
    mass-weighted projection of u0 on the infinitesimal rigid motions (the kernel of K, which neither
    the elastic force nor mass damping can move), returned as the rotation vector w (3,) of u = w x x.

    mass (N,) kg; x (N, 3) m, positions relative to the centre of mass; g (3, 3) the gradient of u0.
    Minimises sum_i m_i |G x_i - w x x_i|^2: (sum m [x]^T [x]) w = sum m [x]^T G x, [x] the matrix of
    x cross. For a body with isotropic second moment and G = R - I about a, w = sin(t) a.
    """

    def cross(v):
        z = np.zeros(len(v))
        return np.stack(
            [
                np.stack([z, -v[:, 2], v[:, 1]], 1),
                np.stack([v[:, 2], z, -v[:, 0]], 1),
                np.stack([-v[:, 1], v[:, 0], z], 1),
            ],
            1,
        )

    c = cross(x)  # c[i] @ w = x_i cross w = -(w cross x_i)
    lhs = np.einsum("i,ikj,ikl->jl", mass, c, c)
    rhs = -np.einsum("i,ikj,ik->j", mass, c, x @ g.T)
    return np.linalg.solve(lhs, rhs)


def _release(model, u0: np.ndarray, alpha: float, period: float, max_steps: int = 400_000) -> np.ndarray:
    """Free damped symplectic Euler from u0 at rest until nothing moves (|v| period < 1e-12 of the size)."""
    integ = SymplecticEuler(alpha, 0.0)
    dt = 0.5 * integ.critical_dt(model)
    state = State(u=u0.copy(), v=np.zeros_like(u0))
    size = float(np.ptp(model.points, axis=0).max())
    while state.steps < max_steps:
        integ.step(model, state, dt, 500)
        if np.abs(state.v).max() * period < 1e-12 * size:
            return state.u
    raise NotConvergedError(f"{model.name}: released rotation still moving after {max_steps} steps")


def global_rotation(size: Size) -> dict:
    out = _finding(
        1,
        "global-rotation",
        "Global rotation",
        "000, slide 18 (Delingette & Ayache 2004)",
        "A body turned rigidly stores elastic energy in the linear model, and released it settles "
        "with a large change of volume; St Venant-Kirchhoff and corotational models store none.",
        "confirmed when, turned 90 degrees, the linear body stores at least half the closed-form energy "
        "2 (lambda + mu)(1 - cos t)^2 V and, released, changes volume by more than 10%, while StVK and "
        "corotational stay below 1e-9 of that energy and of the volume; refuted when the linear body stores "
        "under 1e-9 of it and keeps its volume, or StVK or corotational store or change more than 1%; "
        "nuanced otherwise. (The linear energy's agreement with the closed form checks the implementation: "
        "on an affine field it is exact in P1, so it is reported, not part of the rule.)",
    )
    mesh = get_mesh("box", {"size": [0.04, 0.04, 0.04], "h": size.rotation_h})
    material = Material(young=5.0e4, poisson=0.45, density=1000.0, law="stvk")
    free = Loading.free_body(mesh.n_vertices)
    models = {m: build_model(m, mesh.points, mesh.tets, material, free) for m in TENSOR_MASS}
    mass = models[linear_tm.NAME].mass
    centre = mass @ mesh.points / mass.sum()
    x = mesh.points - centre
    volume = float(signed_volumes(mesh.points, mesh.tets).sum())
    # the slowest elastic mode sets the damping and the settling clock
    k = models[linear_tm.NAME].rest_stiffness().toarray()
    minv = 1.0 / np.sqrt(np.repeat(mass, 3))
    eig = np.linalg.eigvalsh(minv[:, None] * k * minv[None, :])
    omega1 = math.sqrt(eig[eig > 1e-8 * eig[-1]][0])
    rows = [_turned(deg, models, material, mesh, x, volume, omega1) for deg in size.rotation_angles]
    out["table"] = rows
    e_scale = max(r["closed_form_energy_J"] for r in rows) or 1.0
    energy_err = max(abs(r["linear-tm_energy_J"] - r["closed_form_energy_J"]) for r in rows) / e_scale
    others = max(
        max(abs(r[f"{m}_energy_J"]) / e_scale, abs(r[f"{m}_volume_change"])) for r in rows for m in TENSOR_MASS[1:]
    )
    at90 = min(rows, key=lambda r: abs(r["angle_deg"] - 90))
    dv = at90["linear-tm_volume_change"]
    out["data"] = {
        "mesh": {"n_vertices": mesh.n_vertices, "n_tets": mesh.n_tets, "volume_m3": volume},
        "linear_energy_vs_closed_form": energy_err,
        "linear_energy_of_closed_form": at90["linear-tm_energy_J"] / max(at90["closed_form_energy_J"], 1e-300),
        "nonlinear_largest": others,
        "linear_volume_change_at": {"angle_deg": at90["angle_deg"], "value": dv},
        "release_damping_per_s": omega1,
    }
    out["verdict"] = decide(out["data"])
    out["decides"] = (
        f"the released linear body grows by {dv:.1%} at {at90['angle_deg']} degrees (closed form sin^2 = "
        f"{at90['closed_form_volume_change']:.1%}); StVK and corotational stay within {others:.1e}"
    )
    out["figure"] = (
        f"linear energy = 2 (lambda + mu)(1 - cos t)^2 V to {energy_err:.1e}; released volume change "
        f"{dv:+.1%} at {at90['angle_deg']} deg; StVK and corotational {others:.1e}"
    )
    out["reference"] = {"kind": "closed form (rigid motion)", "ref_err_estimate": 0.0, "verified": True}
    out["plots"].append({"alt": "energy and volume change of a rigidly rotated cube", "png": _plot(rows)})
    return out


def decide(data: dict) -> str:
    """The rule (the finding's ``rule``) on the numbers it reads from ``data``: the linear energy at 90
    degrees over the closed form's (linear_energy_of_closed_form), the released linear body's volume
    change there, and the largest energy (relative to the closed form's scale) or volume change of StVK
    and corotational (nonlinear_largest)."""
    stores = data["linear_energy_of_closed_form"]
    dv = data["linear_volume_change_at"]["value"]
    others = data["nonlinear_largest"]
    if stores >= 0.5 and dv > 0.1 and others < 1e-9:
        return "confirmed"
    if (stores < 1e-9 and abs(dv) < 1e-9) or others > 0.01:
        return "refuted"
    return "nuanced"


def _turned(deg: float, models: dict, material, mesh, x: np.ndarray, volume: float, omega1: float) -> dict:
    """One angle's row: the closed forms, and each model's energy when turned and volume change when
    released (``x`` (N, 3) m the vertices about the centre of mass, ``omega1`` 1/s the slowest mode)."""
    mass = models[linear_tm.NAME].mass
    axis = np.array([0.0, 0.0, 1.0])
    t = math.radians(deg)
    g = rotation_matrix(axis, t) - np.eye(3)
    u0 = x @ g.T
    row = {
        "angle_deg": deg,
        "closed_form_energy_J": linear_rotation_energy(material.young, material.poisson, volume, t),
    }
    w = released_rotation(mass, x, g)
    row["closed_form_volume_change"] = math.sin(t) ** 2
    row["projection_volume_change"] = float(w @ w)  # det(I + [w]x) - 1 for the discrete masses
    for name, model in models.items():
        row[f"{name}_energy_J"] = model.elastic_energy(u0)
        settled = _release(model, u0, omega1, 1.0 / omega1)
        row[f"{name}_volume_change"] = _volume_change(mesh.points, mesh.tets, settled)
    log(
        f"seeds 1: {deg} degrees: linear energy {row['linear-tm_energy_J']:.3g} J, volume {row['linear-tm_volume_change']:+.3f}"
    )
    return row


def _plot(rows: list[dict]) -> str:
    """Energy when turned and volume change when released, against the angle, beside the closed forms."""
    angles = [r["angle_deg"] for r in rows]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9.5, 3.4))
    a1.plot(angles, [r["closed_form_energy_J"] * 1e3 for r in rows], "k-", label="closed form, linear")
    for m, mk in zip(TENSOR_MASS, ("o", "s", "^"), strict=True):
        a1.plot(angles, [r[f"{m}_energy_J"] * 1e3 for r in rows], mk, ms=4, fillstyle="none", label=m)
    a1.set_xlabel("rotation (degrees)")
    a1.set_ylabel("elastic energy (mJ)")
    a1.legend(fontsize=7)
    a1.set_title("energy of a rigidly turned cube", fontsize=9)
    a2.plot(angles, [100 * r["closed_form_volume_change"] for r in rows], "k-", label="closed form sin^2, linear")
    for m, mk in zip(TENSOR_MASS, ("o", "s", "^"), strict=True):
        a2.plot(angles, [100 * r[f"{m}_volume_change"] for r in rows], mk, ms=4, fillstyle="none", label=m)
    a2.set_xlabel("rotation (degrees)")
    a2.set_ylabel("volume change after release (%)")
    a2.legend(fontsize=7)
    a2.set_title("released, damped, settled", fontsize=9)
    return png(fig)
