"""The computational backend of the Covariance Intersection family: numpy or compiled numba.

Batched Covariance Intersection (optimal, given and fast weights) and the naive fusion
have two implementations with the same contracts (the same validation and error messages,
conditioning contract, certified gaps, ``converged`` flags and ``info`` keys, results that
agree to the rounding bound of ``docs/backend.rst``, ties broken alike): vectorised numpy,
always available, and compiled kernels (``numba``, the optional extra
``pip install ".[fast]"`` from a clone, ``pip install "cifilter-fusion[fast]"`` once
published), parallel over the batch.

``"auto"`` (the default) uses the kernels when numba is installed, the validated inputs
(float64) are a batch of at least :data:`AUTO_MIN_BATCH` problems and the kernels are
ready; ``"numpy"`` never does; ``"numba"`` always does where a kernel exists (even for one
problem). Importing cifilter never imports numba. Under ``"auto"`` a call never waits for
a compile: kernels not compiled in this process are loaded from numba's on-disk cache when
they are there, and otherwise numpy answers while they compile in a background thread
(started once per process, with one :class:`CompileNotice`); ``python -m cifilter
compile`` (:func:`compile_kernels`) compiles and caches them ahead of time. ``"numba"``
compiles in the foreground on first use (the caller asked for the kernels).
See ``docs/backend.rst``.
"""

import contextlib
import importlib.util
import threading
from collections.abc import Iterator
from typing import Any, Callable, Optional

__all__ = ["AUTO_MIN_BATCH", "BACKENDS", "CompileNotice", "compile_kernels", "get_backend",
           "numba_available", "set_backend", "use_backend"]

BACKENDS = ("auto", "numpy", "numba")
"""The accepted backend names."""

AUTO_MIN_BATCH = 8
"""Under ``"auto"``, batches of at least this many problems go to the compiled kernels.

Measured (``docs/backend.rst``): the kernels are faster than numpy for every batch of 4x4
pairs from 4 problems up. Single fusions of two estimates (no batch axes) take the rule's
short route instead: one compiled call once the kernels are compiled or in numba's cache
(loaded at most once per process, never compiled there), LAPACK directly before that, so a
filter's ``fuse`` never waits for a compile."""



class CompileNotice(UserWarning):
    """Emitted once per process when ``"auto"`` first finds the kernels not compiled.

    The call that emits it, and the next ones, use numpy while the kernels compile in a
    background thread (a minute or two on two cores); then the kernels take over.
    ``python -m cifilter compile`` (:func:`compile_kernels`) compiles and caches them ahead
    of time, after which a new process loads them from the cache without a notice.

    Examples
    --------
    >>> import warnings
    >>> from cifilter.backend import CompileNotice
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("ignore", CompileNotice)  # silence the notice here
    >>> issubclass(CompileNotice, UserWarning)
    True
    """


_state = threading.local()
_compilers: list[Callable[..., Any]] = []
_default = ["auto"]
_available: list[bool] = []


def _check(name):
    if not isinstance(name, str) or name not in BACKENDS:
        raise ValueError(f"backend must be one of {', '.join(map(repr, BACKENDS))}, "
                         f"got {name!r}")
    if name == "numba" and not numba_available():
        raise ValueError("backend 'numba' needs the numba package "
                         "(from a clone: pip install \".[fast]\"; once published: pip install "
                         "\"cifilter-fusion[fast]\"), which is not installed")
    return name


def numba_available() -> bool:
    """Whether numba can be imported (checked once, without importing it).

    Returns
    -------
    bool
        True if the ``numba`` package is installed and not blocked.

    Examples
    --------
    >>> from cifilter.backend import numba_available
    >>> isinstance(numba_available(), bool)
    True
    """
    if not _available:
        import sys

        if "numba" in sys.modules:
            found = sys.modules["numba"] is not None
        else:
            try:
                found = importlib.util.find_spec("numba") is not None
            except (ImportError, ValueError):
                found = False
        _available.append(found)
    return _available[0]


def set_backend(name: str) -> str:
    """Choose the backend of the Covariance Intersection family for this process.

    Parameters
    ----------
    name : {"auto", "numpy", "numba"}
        ``"auto"`` (the default): compiled kernels for float64 batches of at least
        :data:`AUTO_MIN_BATCH` problems when numba is installed, numpy otherwise.
        ``"numpy"``: always numpy. ``"numba"``: the kernels wherever one exists (also for
        a single problem); problems a kernel cannot certify are still solved by numpy.

    Returns
    -------
    str
        The previous backend.

    Raises
    ------
    ValueError
        Unknown name, or ``"numba"`` without numba installed.

    See Also
    --------
    use_backend : the same as a context manager (thread-local).
    get_backend : the backend in effect.

    Examples
    --------
    >>> import cifilter
    >>> previous = cifilter.set_backend("numpy")
    >>> cifilter.get_backend()
    'numpy'
    >>> _ = cifilter.set_backend(previous)
    """
    _check(name)
    previous = get_backend()
    _default[0] = name
    return previous


def get_backend() -> str:
    """The backend in effect in this thread.

    Returns
    -------
    str
        ``"auto"``, ``"numpy"`` or ``"numba"``: the innermost :func:`backend` context of
        this thread, else the process-wide choice of :func:`set_backend`.

    Examples
    --------
    >>> import cifilter
    >>> cifilter.get_backend() in ("auto", "numpy", "numba")
    True
    """
    stack = getattr(_state, "stack", None)
    return stack[-1] if stack else _default[0]


@contextlib.contextmanager
def use_backend(name: str) -> Iterator[str]:
    """Use a backend inside a ``with`` block (this thread only), then restore the previous.

    Parameters
    ----------
    name : {"auto", "numpy", "numba"}
        As in :func:`set_backend`.

    Returns
    -------
    contextmanager
        A context manager; ``with use_backend(name) as chosen`` gives ``chosen == name``.

    Raises
    ------
    ValueError
        Unknown name, or ``"numba"`` without numba installed.

    Examples
    --------
    >>> import numpy as np
    >>> import cifilter
    >>> with cifilter.use_backend("numpy"):
    ...     r = cifilter.covariance_intersection(np.zeros((10, 2, 2)),
    ...                                          np.broadcast_to(np.eye(2), (10, 2, 2, 2)))
    >>> r.omega.shape
    (10, 2)
    """
    _check(name)
    stack = getattr(_state, "stack", None)
    if stack is None:
        stack = _state.stack = []
    stack.append(name)
    try:
        yield name
    finally:
        stack.pop()


def register_compiler(compiler: Callable[..., Any]) -> None:
    """Register the function that compiles every kernel (private to the package: the
    kernels' room registers it, since this module imports nothing of cifilter)."""
    if compiler not in _compilers:
        _compilers.append(compiler)


def compile_kernels(progress: Optional[Callable[[str, float, str], None]] = None
                    ) -> list[tuple[str, float, str]]:
    """Compile every compiled kernel now, in the foreground, and cache it on disk.

    What ``python -m cifilter compile`` runs. Afterwards ``"auto"`` uses the kernels in
    this process, and a new process loads them from numba's on-disk cache (in
    milliseconds) instead of compiling them.

    Parameters
    ----------
    progress : callable, optional
        Called as ``progress(name, seconds, how)`` after each kernel.

    Returns
    -------
    list of (str, float, str)
        Per kernel: its name, the seconds it took, and ``"compiled"``, ``"loaded from
        cache"`` or ``"already compiled"``.

    Raises
    ------
    ValueError
        numba is not installed.

    Examples
    --------
    >>> from cifilter.backend import compile_kernels, numba_available
    >>> if numba_available():  # doctest: +SKIP
    ...     compile_kernels()
    """
    _check("numba")
    if not _compilers:  # pragma: no cover - ``import cifilter`` registers it
        raise RuntimeError("no kernels registered: import cifilter first")
    return list(_compilers[0](**({} if progress is None else {"progress": progress})))


def use_kernels(batch_size: int, *arrays: Any) -> bool:
    """Whether the current backend sends a problem of ``batch_size`` items to the kernels.

    (Private to the package; ``arrays`` must all be float64.)
    """
    name = get_backend()
    if name == "numpy" or not numba_available():
        return False
    if any(getattr(a, "dtype", None) is None or a.dtype.char != "d" for a in arrays):
        return False
    if name == "numba":
        return True
    return batch_size >= AUTO_MIN_BATCH
