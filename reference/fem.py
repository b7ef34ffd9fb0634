"""The reference's elasticity problem: forms and read-outs (``reference.forms``), static solves
(``reference.static``) and Newmark dynamics (``reference.dynamic``) on one object.

Every dolfinx call of tissuebench is in these modules, ``reference.solver`` and
``reference.manufactured`` (dolfinx 0.5.2, Debian's python3-dolfinx).
"""

from __future__ import annotations

from .dynamic import DynamicSolves
from .forms import ProblemForms
from .static import StaticSolves


class ElasticityProblem(ProblemForms, StaticSolves, DynamicSolves):
    """An elasticity problem discretised by dolfinx, with its static and dynamic solves (the arguments
    are ``ProblemForms``'s)."""
