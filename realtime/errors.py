"""The engine's input errors: bad input from a caller, as opposed to a bug.

Every error a user can cause by what they pass (a mesh, a material, a loading, an option) derives from
``InputError``, whose ``str()`` is one line naming the argument, the element or the key, and the value.
The command line turns these, and only these, into exit status 2: any other exception is a bug.
"""

from __future__ import annotations


class InputError(ValueError):
    """Input that cannot be used; ``str()`` is the one-line message."""


class LoadingError(InputError):
    """A Loading or a model option with a wrong shape, dtype, index range or value."""
