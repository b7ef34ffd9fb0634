"""tissuebench's real-time engine: tensor-mass and related soft-tissue models, numba kernels.

Imports only numpy, scipy and numba, so that it can be embedded in a simulator on its own.
"""

import os as _os

# First of all: numba's target, every vector lane the core has (realtime.target), set in the environment
# before numba is loaded, which it reads then; numba fixes its target when it makes its first function.
from . import target as _target  # noqa: F401

# The threaded kernels' threads (realtime.threaded) run in GNU OpenMP, which reads this once, when the
# library loads: a thread that finished its share spins this many times before it sleeps, so that it is
# awake for the next step's force (about a millisecond here; woken from sleep, a thread on this
# machine's virtual cores took longer than the force itself). dolfinx and gmsh load the library too:
# import realtime (or verification) first, or set it yourself.
_os.environ.setdefault("GOMP_SPINCOUNT", "1000000")

from . import jitcache as _jitcache
from .errors import InputError, LoadingError, ModelRestriction
from .integrators import (
    INTEGRATORS,
    CentralDifference,
    DivergenceError,
    ImplicitEuler,
    NotConvergedError,
    SymplecticEuler,
    make_integrator,
)
from .material import Material, MaterialError, Materials
from .model import TOOL_ROTATION, TOOL_TRANSLATION, Loading, Model, State
from .models import MODELS, SPECS, build_model, renumber
from .spectra import element_critical_dt, max_eigenvalue
from .statics import solve_static

_jitcache.guard()

__all__ = [
    "INTEGRATORS",
    "MODELS",
    "SPECS",
    "TOOL_ROTATION",
    "TOOL_TRANSLATION",
    "CentralDifference",
    "DivergenceError",
    "ImplicitEuler",
    "InputError",
    "Loading",
    "LoadingError",
    "Material",
    "MaterialError",
    "Materials",
    "Model",
    "ModelRestriction",
    "NotConvergedError",
    "State",
    "SymplecticEuler",
    "build_model",
    "element_critical_dt",
    "make_integrator",
    "max_eigenvalue",
    "renumber",
    "solve_static",
]
