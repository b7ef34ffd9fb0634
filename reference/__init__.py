"""tissuebench's ground truth: dolfinx solutions of linear and St Venant-Kirchhoff elasticity.

dolfinx is imported lazily (only the dolfinx modules import it: ``fem``, ``forms``, ``solver``, ``static``, ``dynamic``, ``manufactured``), so that the problem description can
be used where dolfinx is absent.
"""

from .problem import Displacement, Fixed, Force, Gravity, Problem, Traction

__all__ = ["Displacement", "Fixed", "Force", "Gravity", "Problem", "Traction"]
