"""The reference's own failure, importable without dolfinx (the command line catches it)."""


class ReferenceSolveError(RuntimeError):
    """The reference could not solve the problem as stated (Newton failed at a load fraction, a singular
    system...); ``str()`` is one line saying where it stopped and what the user can change."""
