"""Material description and every conversion between elastic constants.

This is the one module of ``realtime`` that ``reference`` and ``verification`` import: pure data and
numpy, so that the ground truth and the real-time engine can never disagree on what a scene's
``young``/``poisson`` mean.

Conventions (Delingette & Ayache 2004, section 2; any continuum mechanics text):

    lambda = E nu / ((1 + nu)(1 - 2 nu))        first Lame coefficient, Pa
    mu     = E / (2 (1 + nu))                   shear modulus, Pa
    E      = mu (3 lambda + 2 mu) / (lambda + mu)
    nu     = lambda / (2 (lambda + mu))
    K      = E / (3 (1 - 2 nu))                 bulk modulus, Pa
    M      = lambda + 2 mu                      P-wave (oedometric) modulus, Pa
    c_p    = sqrt(M / rho)                      dilatational wave speed, m/s

Transversely isotropic materials (Picinbono, Delingette & Ayache 2003) add to the isotropic energy
density the terms ``dlambda/2 (a.E a)^2 + dmu (a.E^2 a)`` for a unit fibre direction ``a``. The scene
gives ``young_fiber``, the Young's modulus measured in uniaxial stress along the fibre, and
``fiber_shear`` = dmu (default 0). In uniaxial stress along ``a`` the lateral strains are those of the
isotropic material (-nu eps, since neither fibre term acts across the fibre when the strain is
diagonal), and the stress along the fibre is

    sigma = (E + dlambda + 2 dmu) eps

(dlambda from the (a.E a)^2 term, 2 dmu from |E a|^2), so this module defines

    dlambda = young_fiber - young - 2 fiber_shear,   dmu = fiber_shear,

which makes ``young_fiber`` mean what its name says whatever ``fiber_shear`` is. The shear modulus in a
plane that holds the fibre is then mu + dmu/2; across it, mu. Tests check each by the experiment that
defines it (uniaxial stress, simple shear) on both the engine's laws and the reference's.

The fibres run along one direction ``fiber`` everywhere, or around an axis (``fiber_axis`` through
``fiber_point``: circumferential fibres, a vessel's or an intestine's smooth muscle), where the direction
at x is a(x) = t / |t|, t = axis x (x - point). ``fiber_directions`` evaluates either at points: the
engine at each tetrahedron's centroid, the reference at its quadrature points (the continuous field).

The volume penalty (Picinbono 2003, "incompressibility constraint") is the energy-consistent term
``volume_penalty/2 (J - 1)^2`` per unit reference volume, J = det F, coefficient in Pa.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError, is_real

#: The laws of the ground truth; the fibre terms are the linear and StVK laws' (Picinbono et al. 2003).
LAWS = ("linear", "stvk", "neo-hookean", "stable-neo-hookean", "stable-neo-hookean-no-log")
FIBRE_LAWS = ("linear", "stvk")


class MaterialError(InputError):
    """An elastic constant outside its physical range; the message names it and its value."""


def lame_lambda(young: float, poisson: float) -> float:
    """First Lame coefficient lambda = E nu / ((1 + nu)(1 - 2 nu)), Pa."""
    return young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))


def shear_modulus(young: float, poisson: float) -> float:
    """Shear modulus mu = E / (2 (1 + nu)), Pa."""
    return young / (2.0 * (1.0 + poisson))


def young_from_lame(lam: float, mu: float) -> float:
    """Young's modulus E = mu (3 lambda + 2 mu) / (lambda + mu), Pa."""
    return mu * (3.0 * lam + 2.0 * mu) / (lam + mu)


def poisson_from_lame(lam: float, mu: float) -> float:
    """Poisson's ratio nu = lambda / (2 (lambda + mu))."""
    return lam / (2.0 * (lam + mu))


def bulk_modulus(young: float, poisson: float) -> float:
    """Bulk modulus K = E / (3 (1 - 2 nu)), Pa."""
    return young / (3.0 * (1.0 - 2.0 * poisson))


def p_wave_modulus(young: float, poisson: float) -> float:
    """P-wave modulus lambda + 2 mu = E (1 - nu) / ((1 + nu)(1 - 2 nu)), Pa."""
    return young * (1.0 - poisson) / ((1.0 + poisson) * (1.0 - 2.0 * poisson))


def fiber_lambda(young: float, young_fiber: float, fiber_shear: float = 0.0) -> float:
    """Picinbono's extra fibre coefficient dlambda = young_fiber - young - 2 fiber_shear, Pa (see the
    module docstring: uniaxial stress along the fibre is then young_fiber times the strain)."""
    return young_fiber - young - 2.0 * fiber_shear


def check_elastic_constants(young: float, poisson: float, density: float) -> None:
    """Raise MaterialError unless E > 0, -1 < nu < 0.5 and rho > 0, each a number."""
    for name, value in (("young", young), ("poisson", poisson), ("density", density)):
        if not is_real(value):
            raise MaterialError(f"{name} = {value!r}: must be a number, got {type(value).__name__}")
    if not (math.isfinite(young) and young > 0.0):
        raise MaterialError(f"young = {young!r}: Young's modulus must be a positive number of Pa")
    if not (math.isfinite(poisson) and -1.0 < poisson < 0.5):
        raise MaterialError(
            f"poisson = {poisson!r}: Poisson's ratio must lie in (-1, 0.5); 0.5 is incompressible, "
            "which a displacement formulation cannot represent (use 0.4999 or volume_penalty)"
        )
    if not (math.isfinite(density) and density > 0.0):
        raise MaterialError(f"density = {density!r}: must be a positive number of kg/m^3")


@dataclass(frozen=True)
class Material:
    """An elastic material in SI units.

    Attributes:
        young: Young's modulus E, Pa.
        poisson: Poisson's ratio nu, dimensionless, in (-1, 0.5).
        density: mass density rho, kg/m^3.
        law: continuum model of the ground truth, one of LAWS: "linear", "stvk", "neo-hookean"
            (compressible, isotropic: no fibres) or the stable neo-Hookean laws newton's tetrahedra run
            (Smith et al. 2018, with and without the log term; isotropic).
        fiber: unit fibre direction a (3,) for a transversely isotropic material, or None.
        fiber_axis: instead of ``fiber``, fibres around this axis (3,) (circumferential), or None.
        fiber_point: a point (3,) m of that axis (default the origin).
        young_fiber: Young's modulus along the fibre, Pa (None: isotropic).
        fiber_shear: Picinbono's dmu, Pa (0 unless given).
        volume_penalty: coefficient of the energy volume_penalty/2 (J - 1)^2, Pa.
    """

    young: float
    poisson: float
    density: float
    law: str = "linear"
    fiber: tuple[float, float, float] | None = None
    young_fiber: float | None = None
    fiber_shear: float = 0.0
    volume_penalty: float = 0.0
    fiber_axis: tuple[float, float, float] | None = None
    fiber_point: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        check_elastic_constants(self.young, self.poisson, self.density)
        if self.law not in LAWS:
            raise MaterialError(f"law = {self.law!r}: must be one of {', '.join(LAWS)}")
        if self.volume_penalty < 0.0 or not math.isfinite(self.volume_penalty):
            raise MaterialError(f"volume_penalty = {self.volume_penalty!r}: must be >= 0 Pa")
        if self.fiber is not None and self.fiber_axis is not None:
            raise MaterialError("fiber and fiber_axis: give one fibre direction or one axis to run around, not both")
        if (self.fiber is None and self.fiber_axis is None) != (self.young_fiber is None):
            raise MaterialError(
                "fiber and young_fiber go together: give both or neither (or fiber_axis and young_fiber)"
            )
        for name in ("fiber", "fiber_axis"):
            value = getattr(self, name)
            if value is None:
                continue
            a = np.asarray(value, dtype=float)
            norm = float(np.linalg.norm(a)) if a.shape == (3,) else 0.0
            if not (math.isfinite(norm) and norm > 0.0):
                raise MaterialError(f"{name} = {value!r}: must be a non-zero 3-vector")
            object.__setattr__(self, name, tuple(float(x) for x in a / norm))
        point = np.asarray(self.fiber_point, dtype=float)
        if point.shape != (3,) or not np.all(np.isfinite(point)):
            raise MaterialError(f"fiber_point = {self.fiber_point!r}: must be a finite 3-vector, m")
        object.__setattr__(self, "fiber_point", tuple(float(x) for x in point))
        if self.transverse:
            if self.law not in FIBRE_LAWS:
                raise MaterialError(
                    f"law = {self.law!r} with fibres: the fibre terms are those of {' and '.join(FIBRE_LAWS)}; "
                    "give an isotropic material or one of those laws"
                )
            if not (math.isfinite(self.young_fiber) and self.young_fiber > 0.0):
                raise MaterialError(f"young_fiber = {self.young_fiber!r}: must be a positive number of Pa")
            if not (math.isfinite(self.fiber_shear) and self.mu + 0.5 * self.fiber_shear > 0.0):
                raise MaterialError(
                    f"fiber_shear = {self.fiber_shear!r}: the shear modulus along the fibre, mu + fiber_shear/2, "
                    f"must be > 0 (mu = {self.mu:.6g} Pa)"
                )

    @property
    def lam(self) -> float:
        """First Lame coefficient, Pa."""
        return lame_lambda(self.young, self.poisson)

    @property
    def mu(self) -> float:
        """Shear modulus, Pa."""
        return shear_modulus(self.young, self.poisson)

    @property
    def transverse(self) -> bool:
        """True for a transversely isotropic material (fibres along a direction or around an axis)."""
        return self.fiber is not None or self.fiber_axis is not None

    @property
    def dlam(self) -> float:
        """Fibre coefficient dlambda, Pa (0 for an isotropic material)."""
        return 0.0 if self.young_fiber is None else fiber_lambda(self.young, self.young_fiber, self.fiber_shear)

    @property
    def dmu(self) -> float:
        """Fibre shear coefficient dmu, Pa (0 for an isotropic material)."""
        return self.fiber_shear if self.transverse else 0.0

    @property
    def fiber_vector(self) -> np.ndarray:
        """The one fibre direction (3,) float64; zeros for an isotropic material. Fibres around an axis
        have none: ``fiber_directions`` gives theirs."""
        if self.fiber_axis is not None:
            raise MaterialError("fiber_axis: fibres around an axis change direction; use fiber_directions(points)")
        return np.zeros(3) if self.fiber is None else np.asarray(self.fiber, dtype=float)

    def fiber_directions(self, x: np.ndarray) -> np.ndarray:
        """Unit fibre directions (K, 3) float64 at points x (K, 3) m: ``fiber`` everywhere, or around
        ``fiber_axis``: axis x (x - fiber_point), normalised; zeros for an isotropic material and on the
        axis itself, where the circumferential direction is undefined (the law is isotropic there)."""
        x = np.asarray(x, dtype=float).reshape(-1, 3)
        if self.fiber_axis is None:
            return np.broadcast_to(self.fiber_vector, x.shape).copy()
        t = np.cross(np.asarray(self.fiber_axis), x - np.asarray(self.fiber_point))
        norm = np.linalg.norm(t, axis=1)
        out = np.zeros_like(t)
        ok = norm > 1e-12 * max(1.0, float(np.abs(x).max(initial=0.0)))
        out[ok] = t[ok] / norm[ok, None]
        return out

    @property
    def wave_speed(self) -> float:
        """Largest dilatational wave speed c_p = sqrt(max modulus / rho), m/s.

        Includes the fibre stiffening and the volume penalty, which both raise the P-wave modulus.
        """
        modulus = p_wave_modulus(self.young, self.poisson) + max(self.dlam, 0.0)
        modulus += 2.0 * max(self.dmu, 0.0) + self.volume_penalty
        return math.sqrt(modulus / self.density)

    def replace(self, **changes) -> Material:
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict:
        """JSON-ready description, for result metadata and hashing."""
        return {
            "young": self.young,
            "poisson": self.poisson,
            "density": self.density,
            "law": self.law,
            "fiber": list(self.fiber) if self.fiber is not None else None,
            "young_fiber": self.young_fiber,
            "fiber_shear": self.fiber_shear,
            "volume_penalty": self.volume_penalty,
            "fiber_axis": list(self.fiber_axis) if self.fiber_axis is not None else None,
            "fiber_point": list(self.fiber_point),
        }


#: The Material fields a tetrahedron's coefficient can be read from (``Materials.per_tet``).
PER_TET = ("young", "poisson", "density", "lam", "mu", "dlam", "dmu", "volume_penalty", "wave_speed")


@dataclass(frozen=True, eq=False)
class Materials:
    """Several materials in one body, one for each tetrahedron: a tumour in a liver, layered skin, fat
    and muscle. Every engine model takes it wherever it takes a Material; a Material is one material
    everywhere (``Materials.of``).

    Attributes:
        materials: the distinct materials, a tuple of K Material.
        index: (M,) int64, the material of each tetrahedron of the mesh, in 0 .. K-1 (read-only).
    """

    materials: tuple
    index: np.ndarray

    def __post_init__(self) -> None:
        materials = tuple(self.materials)
        if not materials or not all(isinstance(m, Material) for m in materials):
            raise MaterialError(f"materials: a non-empty sequence of Material, got {self.materials!r:.80}")
        index = np.asarray(self.index)
        if index.ndim != 1 or not (np.issubdtype(index.dtype, np.integer) or len(index) == 0):
            raise MaterialError(
                f"materials.index: a 1-D integer array (one per tetrahedron), got {index.dtype} {index.shape}"
            )
        index = index.astype(np.int64)
        bad = np.flatnonzero((index < 0) | (index >= len(materials)))
        if len(bad):
            raise MaterialError(
                f"materials.index[{bad[0]}] = {index[bad[0]]}: tetrahedron {bad[0]} names no material "
                f"(there are {len(materials)})"
            )
        index.flags.writeable = False
        object.__setattr__(self, "materials", materials)
        object.__setattr__(self, "index", index)

    @staticmethod
    def of(material: Material | Materials, n_tets: int) -> Materials:
        """The per-tetrahedron form of ``material`` for a mesh of ``n_tets`` tetrahedra: a Material
        everywhere, or a Materials checked to have one entry per tetrahedron."""
        if isinstance(material, Materials):
            if len(material.index) != n_tets:
                raise MaterialError(f"materials.index: {len(material.index)} entries for a mesh of {n_tets} tetrahedra")
            return material
        if not isinstance(material, Material):
            raise MaterialError(f"material: a Material or Materials, got {type(material).__name__}")
        return Materials((material,), np.zeros(n_tets, dtype=np.int64))

    def per_tet(self, name: str) -> np.ndarray:
        """Each tetrahedron's value (M,) float64 of the Material field or property ``name`` (one of
        PER_TET, in its SI unit)."""
        if name not in PER_TET:
            raise MaterialError(f"per_tet({name!r}): one of {', '.join(PER_TET)}")
        return np.array([float(getattr(m, name)) for m in self.materials])[self.index]

    def fiber_directions(self, centroids: np.ndarray) -> np.ndarray:
        """Unit fibre directions (M, 3) float64 of each tetrahedron's material at its centroid (M, 3) m
        (``Material.fiber_directions``; zeros where the material is isotropic)."""
        centroids = np.asarray(centroids, dtype=float).reshape(-1, 3)
        out = np.zeros_like(centroids)
        for k, m in enumerate(self.materials):
            sel = self.index == k
            out[sel] = m.fiber_directions(centroids[sel])
        return out

    def subset(self, which) -> Materials:
        """The materials of tetrahedra ``which`` (an index or mask of the mesh's tetrahedra), in order."""
        return Materials(self.materials, self.index[which])

    @property
    def transverse(self) -> bool:
        """True if any material has fibres."""
        return any(m.transverse for m in self.materials)

    @property
    def homogeneous(self) -> bool:
        """True if every tetrahedron has the same material."""
        return len(np.unique(self.index)) <= 1

    def as_dict(self) -> dict:
        """JSON-ready description: the materials and how many tetrahedra each has."""
        counts = np.bincount(self.index, minlength=len(self.materials))
        return {"materials": [m.as_dict() for m in self.materials], "tets": [int(c) for c in counts]}
