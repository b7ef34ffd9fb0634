"""realtime.material: conversions between elastic constants and the fibre parameters."""

import math

import numpy as np
import pytest

from realtime.laws import linear_elasticity_tensor
from realtime.material import (
    Material,
    MaterialError,
    bulk_modulus,
    lame_lambda,
    p_wave_modulus,
    poisson_from_lame,
    shear_modulus,
    young_from_lame,
)

EPS = np.finfo(float).eps


@pytest.mark.parametrize("E, nu", [(1e3, 0.0), (5e5, 0.45), (1e7, 0.3), (2.8e4, 0.4), (1e4, 0.4999)])
def test_round_trip(E, nu):
    lam, mu = lame_lambda(E, nu), shear_modulus(E, nu)
    # a handful of operations, with cancellation 1 - 2 nu at nu -> 0.5: a few thousand eps
    assert young_from_lame(lam, mu) == pytest.approx(E, rel=1e4 * EPS)
    assert poisson_from_lame(lam, mu) == pytest.approx(nu, rel=1e4 * EPS, abs=1e4 * EPS)
    assert p_wave_modulus(E, nu) == pytest.approx(lam + 2 * mu, rel=1e4 * EPS)
    assert bulk_modulus(E, nu) == pytest.approx(lam + 2 * mu / 3, rel=1e4 * EPS)


def test_picinbono_liver_constants():
    # Picinbono et al. 2003: lambda = 40 kPa, mu = 10 kPa is E = 28 kPa, nu = 0.4
    assert young_from_lame(40e3, 10e3) == pytest.approx(28e3, rel=10 * EPS)
    assert poisson_from_lame(40e3, 10e3) == pytest.approx(0.4, rel=10 * EPS)


@pytest.mark.parametrize(
    "field, value",
    [
        ("poisson", 0.5),
        ("poisson", 0.7),
        ("poisson", -1.0),
        ("young", 0.0),
        ("young", -5.0),
        ("density", 0.0),
        ("young", math.nan),
        ("young", "5e5"),  # a TypeError from math.isfinite before
        ("density", None),
        ("poisson", True),
    ],
)
def test_bad_constants_name_the_field(field, value):
    kwargs = {"young": 1e4, "poisson": 0.3, "density": 1000.0, field: value}
    with pytest.raises(MaterialError, match=field):
        Material(**kwargs)


def _uniaxial_modulus(C, direction):
    """Young's modulus in uniaxial stress along a unit direction: 1 / (d.d : S : d.d)."""
    c66 = C.reshape(9, 9)
    S = np.linalg.pinv(c66)
    dd = np.outer(direction, direction).ravel()
    return 1.0 / (dd @ S @ dd)


def test_young_fiber_is_the_stiffness_along_the_fibre():
    m = Material(1e4, 0.4, 1000.0, fiber=(0.0, 0.0, 2.0), young_fiber=9e3 + 1e4)
    assert m.fiber == (0.0, 0.0, 1.0)
    C = linear_elasticity_tensor(m.lam, m.mu, m.fiber_vector, m.dlam, m.dmu)
    assert _uniaxial_modulus(C, np.array([0, 0, 1.0])) == pytest.approx(1.9e4, rel=1e-10)
    # across the fibre the modulus stays near E (the fibre term couples through Poisson only)
    across = _uniaxial_modulus(C, np.array([1.0, 0, 0]))
    assert 1e4 <= across < 1.9e4


def test_fiber_needs_both_keys():
    with pytest.raises(MaterialError, match="fiber and young_fiber"):
        Material(1e4, 0.3, 1000.0, fiber=(1, 0, 0))


def test_fibres_around_an_axis():
    m = Material(1e4, 0.3, 1000.0, fiber_axis=(0.0, 0.0, 2.0), fiber_point=(1.0, 0.0, 0.0), young_fiber=3e4)
    x = np.array([[2.0, 0.0, 5.0], [1.0, -3.0, 0.0], [1.0, 0.0, 7.0]])
    a = m.fiber_directions(x)
    # around the line x = 1, y = 0 along z: tangent to the circle through each point, counter-clockwise;
    # on the axis itself there is no direction, and the law is isotropic there
    np.testing.assert_allclose(a, [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]], atol=1e-15)
    assert m.transverse and m.dlam == pytest.approx(3e4 - 1e4) and m.fiber_axis == (0.0, 0.0, 1.0)
    with pytest.raises(MaterialError, match="fiber_directions"):
        m.fiber_vector  # noqa: B018  (the property raises)
    with pytest.raises(MaterialError, match="not both"):
        Material(1e4, 0.3, 1000.0, fiber=(1.0, 0.0, 0.0), fiber_axis=(0.0, 0.0, 1.0), young_fiber=3e4)
    with pytest.raises(MaterialError, match="fiber_axis = "):
        Material(1e4, 0.3, 1000.0, fiber_axis=(0.0, 0.0, 0.0), young_fiber=3e4)
    with pytest.raises(MaterialError, match="young_fiber go together"):
        Material(1e4, 0.3, 1000.0, fiber_axis=(0.0, 0.0, 1.0))
