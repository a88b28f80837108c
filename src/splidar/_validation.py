"""Private input validators shared by every module.

Every error names the parameter, the expected form and what was received, and
suggests a fix where one is obvious. Public functions call these instead of
writing their own checks, so that messages stay consistent across the library.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = [
    "SplidarError",
    "as_float_array",
    "check_choice",
    "check_in_range",
    "check_int",
    "check_ndim",
    "check_positive",
    "check_probability",
    "describe",
]


class SplidarError(ValueError):
    """Invalid input to a splidar function.

    A subclass of :class:`ValueError`, so ``except ValueError`` keeps working;
    the command line turns it into one line on stderr and a non-zero exit.
    """


def describe(x: Any) -> str:
    """Short description of a received value for error messages."""
    if isinstance(x, np.ndarray):
        return f"an array of shape {x.shape} and dtype {x.dtype}"
    if isinstance(x, (list, tuple)):
        return f"a {type(x).__name__} of length {len(x)}"
    r = repr(x)
    if len(r) > 60:
        r = r[:57] + "..."
    return f"{r} ({type(x).__name__})"


def check_ndim(a: np.ndarray, name: str, ndims: Sequence[int], form: str) -> None:
    """Raise if ``a.ndim`` is not one of ``ndims``; ``form`` spells the expected shape."""
    if a.ndim not in ndims:
        raise SplidarError(
            f"`{name}` must have shape {form}; got {a.ndim} dimension(s) with shape {a.shape}."
        )


def as_float_array(x: Any, name: str, *, dtype=np.float64, finite: bool = True) -> np.ndarray:
    """Convert to a float array, refusing non-numeric input and (optionally) NaN/inf."""
    try:
        a = np.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise SplidarError(
            f"`{name}` must be numeric array-like; got {describe(x)} ({exc})."
        ) from None
    if finite and a.size and not np.all(np.isfinite(a)):
        n = int(np.count_nonzero(~np.isfinite(a)))
        raise SplidarError(
            f"`{name}` must be finite; it holds {n} NaN or infinite value(s). "
            "Replace them (e.g. np.nan_to_num) before calling."
        )
    return a


def check_int(x: Any, name: str, *, minimum: int | None = None) -> int:
    """Return ``x`` as an int, refusing bools, floats with a fraction and values below minimum."""
    if isinstance(x, bool) or not isinstance(x, (numbers.Integral, np.integer)):
        if isinstance(x, (float, np.floating)) and float(x).is_integer():
            x = int(x)
        else:
            raise SplidarError(f"`{name}` must be an integer; got {describe(x)}.")
    x = int(x)
    if minimum is not None and x < minimum:
        raise SplidarError(f"`{name}` must be >= {minimum}; got {x}.")
    return x


def check_positive(x: Any, name: str, *, allow_zero: bool = False) -> float:
    """Return ``x`` as a finite float > 0 (or >= 0 with ``allow_zero``)."""
    if isinstance(x, bool) or not isinstance(x, (numbers.Real, np.floating, np.integer)):
        raise SplidarError(f"`{name}` must be a real number; got {describe(x)}.")
    x = float(x)
    ok = np.isfinite(x) and (x >= 0 if allow_zero else x > 0)
    if not ok:
        bound = ">= 0" if allow_zero else "> 0"
        raise SplidarError(f"`{name}` must be a finite number {bound}; got {x!r}.")
    return x


def check_in_range(
    x: Any, name: str, lo: float, hi: float, *, lo_open: bool = False, hi_open: bool = False
) -> float:
    """Return ``x`` as float inside [lo, hi] (ends open as requested)."""
    if isinstance(x, bool) or not isinstance(x, (numbers.Real, np.floating, np.integer)):
        raise SplidarError(f"`{name}` must be a real number; got {describe(x)}.")
    x = float(x)
    bad = not np.isfinite(x) or (x <= lo if lo_open else x < lo) or (x >= hi if hi_open else x > hi)
    if bad:
        left = "(" if lo_open else "["
        right = ")" if hi_open else "]"
        raise SplidarError(f"`{name}` must lie in {left}{lo}, {hi}{right}; got {x!r}.")
    return x


def check_probability(x: Any, name: str) -> float:
    """A probability strictly between 0 and 1 (e.g. a false-alarm rate)."""
    return check_in_range(x, name, 0.0, 1.0, lo_open=True, hi_open=True)


def check_choice(x: Any, name: str, choices: Sequence[str]) -> str:
    """Return ``x`` if it is one of ``choices``; otherwise list them."""
    if x not in choices:
        opts = ", ".join(repr(c) for c in choices)
        raise SplidarError(f"`{name}` must be one of {opts}; got {x!r}.")
    return x
