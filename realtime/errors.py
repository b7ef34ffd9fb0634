"""The engine's input errors: bad input from a caller, as opposed to a bug.

Every error a user can cause by what they pass (a mesh, a material, a loading, an option) derives from
``InputError``, whose ``str()`` is one line naming the argument, the element or the key, and the value.
The command line turns these, and only these, into exit status 2: any other exception is a bug.
"""

from __future__ import annotations

import numpy as np


class InputError(ValueError):
    """Input that cannot be used; ``str()`` is the one-line message."""


class ModelRestriction(InputError):
    """A scene this model cannot represent, whose input is otherwise fine (precomputed's responses exist
    for surface vertices only): one command still stops on it, a study of many models records it as that
    model's answer and goes on with the others."""


class LoadingError(InputError):
    """A Loading or a model option with a wrong shape, dtype, index range or value."""


def did_you_mean(word: str, choices) -> str:
    """ " (did you mean 'x'?)" naming the choice closest to a mistyped ``word`` (difflib's ratio of at
    least 0.6), or "" where none is close: the end of an error's line."""
    import difflib

    near = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1)
    return f" (did you mean {near[0]!r}?)" if near else ""


def is_real(value) -> bool:
    """Whether ``value`` is a real number: a Python or numpy int or float, not a bool (a flag passed
    where a number belongs) and not a string."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def float_array(what: str, value, dtype=np.float64, kind: str = "an array", error: type[InputError] = InputError):
    """``value`` as a C-contiguous array of ``dtype`` (a copy only where needed), or ``error`` saying
    "{what}: must be {kind} of numbers" and the type it got (a string, None, a ragged list)."""
    try:
        a = np.asarray(value, dtype=dtype)  # not ascontiguousarray, which makes a scalar 1-D
    except (TypeError, ValueError):
        raise error(f"{what}: must be {kind} of numbers, got {type(value).__name__}") from None
    return a if a.flags.c_contiguous else np.ascontiguousarray(a)


def whole_numbers(what: str, value, error: type[InputError] = InputError) -> np.ndarray:
    """``value`` as an int64 array, or ``error`` naming ``what`` and the first entry that is not a whole
    number (numpy's astype would truncate 0.5 to 0, and a string is its ValueError)."""
    a = np.asarray(value)
    if a.dtype.kind not in "iu" and a.size:
        whole = (np.isfinite(a) & (a == np.round(a))) if a.dtype.kind == "f" else np.zeros(a.shape, bool)
        if not whole.all():
            raise error(f"{what}: must be whole-number indices, got {a.ravel()[np.argmin(whole.ravel())]!r}")
    return a.astype(np.int64)


def index_array(what: str, value, n: int, width: int | None = None, error: type[InputError] = InputError) -> np.ndarray:
    """``value`` as an int64 array of indices into n things ((K,), or (K, width) if ``width``), or
    ``error`` naming ``what`` and the first bad entry: indices must be whole numbers (numpy would
    truncate 0.5 to 0) in 0 .. n - 1 (numpy would take -1 as the last one)."""
    a = whole_numbers(what, value, error)
    if a.size == 0:
        return np.zeros((0,) if width is None else (0, width), np.int64)
    if width is not None:
        if a.ndim == 1 and a.size == width:
            a = a.reshape(1, width)
        if a.ndim != 2 or a.shape[1] != width:
            raise error(f"{what}: must have shape (K, {width}), got {np.shape(value)}")
    elif a.ndim > 1:
        raise error(f"{what}: must be a list of indices, got shape {a.shape}")
    bad = (a < 0) | (a >= n)
    if bad.any():
        first = a.reshape(len(a), -1)[np.any(bad.reshape(len(a), -1), axis=1)][0]
        shown = first.tolist() if width is not None else int(first[0])
        raise error(f"{what}: {shown} is outside 0..{n - 1}")
    return a.reshape(-1) if width is None else a
