"""Material laws: stress against finite differences of energy; analytic StVK states."""

import math

import numpy as np
import pytest

from realtime.laws import linear_energy, linear_pk1, stvk_energy, stvk_pk1, volume_penalty_energy, volume_penalty_pk1

LAM, MU = 4e4, 1e4
A = np.array([0.6, 0.0, 0.8])


def _fd_stress(W, F, h=1e-6):
    P = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            d = np.zeros((3, 3))
            d[i, j] = h
            P[i, j] = (W(F + d) - W(F - d)) / (2 * h)
    return P


@pytest.mark.parametrize("dlam, dmu", [(0.0, 0.0), (3e4, 5e3)])
@pytest.mark.parametrize("law", ["linear", "stvk", "penalty"])
def test_stress_is_energy_gradient(law, dlam, dmu, rng):
    F = np.eye(3) + 0.3 * rng.standard_normal((3, 3))
    if law == "linear":
        W, P = (lambda G: linear_energy(G, LAM, MU, A, dlam, dmu)), linear_pk1(F, LAM, MU, A, dlam, dmu)
    elif law == "stvk":
        W, P = (lambda G: stvk_energy(G, LAM, MU, A, dlam, dmu)), stvk_pk1(F, LAM, MU, A, dlam, dmu)
    else:
        W, P = (lambda G: volume_penalty_energy(G, 5e4)), volume_penalty_pk1(F, 5e4)
    # central differences of a polynomial energy of degree <= 4: truncation ~ h^2 |W'''| ~ 1e-12 P,
    # round-off ~ eps W / h ~ 1e-10 P; 1e-7 leaves margin for both
    np.testing.assert_allclose(P, _fd_stress(W, F), rtol=1e-7, atol=1e-7 * np.abs(P).max())


@pytest.mark.parametrize("angle", [30.0, 90.0, 180.0])
def test_stvk_rigid_rotation_is_stress_free(angle):
    th = math.radians(angle)
    R = np.array([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1.0]])
    P = stvk_pk1(R, LAM, MU, A, 3e4, 5e3)
    assert np.abs(P).max() < 1e3 * np.finfo(float).eps * LAM  # E = (R^T R - I)/2 is round-off


@pytest.mark.parametrize("s", [0.7, 1.2, 1.5])
def test_stvk_uniaxial_stretch(s):
    """P11 = E s (s^2 - 1) / 2 with lateral stretch t^2 = 1 - nu (s^2 - 1) (docs/verification.md)."""
    E = MU * (3 * LAM + 2 * MU) / (LAM + MU)
    nu = LAM / (2 * (LAM + MU))
    t = math.sqrt(1 - nu * (s * s - 1))
    P = stvk_pk1(np.diag([s, t, t]), LAM, MU, np.zeros(3), 0.0, 0.0)
    assert P[0, 0] == pytest.approx(E * s * (s * s - 1) / 2, rel=1e-12)
    assert abs(P[1, 1]) < 1e-10 * E and abs(P[2, 2]) < 1e-10 * E
