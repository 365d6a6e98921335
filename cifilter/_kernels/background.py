"""Readiness of the compiled kernels: loaded from numba's on-disk cache, or compiled in a
background thread, so that a call under ``"auto"`` never waits for a compile.

The kernels of :mod:`cifilter._kernels.compiled` are compiled for one signature each (the
dispatch passes C-contiguous, writeable float64 arrays, ``int8`` status and ``int64``
iteration counts, whatever ``n`` and the batch size). :func:`ready` answers, without
compiling, whether every kernel can run now: already compiled in this process, or loadable
from numba's cache (then it is loaded, which takes milliseconds). When not, the first call
starts :func:`compile_all` once per process in a daemon thread and emits one
:class:`cifilter.backend.CompileNotice`; the caller keeps to the numpy path until the
thread has finished. ``python -m cifilter compile`` runs :func:`compile_all` in the
foreground (through :func:`cifilter.backend.compile_kernels`).
"""

import os
import sys
import threading
import time
import warnings
from pathlib import Path
from types import FrameType
from typing import Any, Callable, Optional

import numpy as np

from ..backend import CompileNotice, register_compiler

__all__ = ["KERNELS", "compile_all", "loaded", "ready", "status"]

KERNELS = ("ci_pair", "ci_pair_serial", "weighted_fusion",
           "weighted_fusion_serial", "ci_many_optimal", "ci_many_optimal_serial",
           "generalised_pair", "shifted_pair")
"""The kernels the dispatch calls (each compiled for one signature)."""

_lock = threading.Lock()
_state: dict[str, Any] = {"ready": False, "started": False, "thread": None, "error": None,
                          "compiled": [], "tried_loading": False}


def _arguments(name: str) -> tuple:
    """Arguments of the types the dispatch passes to kernel ``name`` (one problem, n = 2)."""
    n, size = 2, 1
    eye = np.ascontiguousarray(np.broadcast_to(np.eye(n), (size, n, n)))
    P, L = eye.copy(), eye.copy()
    W = np.zeros((1, 1, 1))
    value, log_value = np.empty(size), np.empty(size)
    status = np.empty(size, dtype=np.int8)
    if name.startswith("ci_pair"):
        x2, P2, L2 = np.zeros((size, 2, n)), np.stack([P, P], axis=1), np.stack([L, L], axis=1)
        return (x2, P2, L2, W, 0, 0, np.empty((size, 8)), np.empty((size, n)),
                np.empty((size, n, n)), np.empty((size, 2, n, n)))
    if name == "shifted_pair":  # (dispatch.shifted_pair_single's: M, N read-only)
        M, N = eye[0].copy(), eye[0].copy()
        M.flags.writeable = N.flags.writeable = False
        x2, P2 = np.zeros((size, 2, n)), np.stack([P, P], axis=1)
        return (x2, P2, 0, M, N, True, W, 0, 0, np.empty((size, 8)), np.empty((size, n)),
                np.empty((size, n, n)), np.empty((size, 2, n, n)))
    if name == "generalised_pair":  # (_kernels.generalised.partial_pair's arguments)
        xb, Pb = np.zeros(1), np.eye(1)
        return (np.zeros(n), eye[0].copy(), eye[0].copy(), xb, Pb, Pb.copy(),
                np.zeros((1, n)), W, 0, True, np.empty(n), np.empty((n, n)),
                np.empty((n, n)), np.empty((n, 1)), np.zeros(5))
    if name.startswith("ci_many_optimal"):
        count = 3
        x3, L3 = np.zeros((size, count, n)), np.stack([L, L, L], axis=1)
        gap, floor, computed = (np.empty(size) for _ in range(3))
        return (x3, L3, W, 0, np.zeros((size, count)), np.zeros(size, dtype=int), gap, floor,
                computed, np.empty((size, n)), np.empty((size, n, n)),
                np.empty((size, count, n, n)), value, log_value, status,
                np.zeros(size, dtype=np.int64))
    x2, L2 = np.zeros((size, 2, n)), np.stack([L, L], axis=1)
    weights = np.full((size, 2), 0.5)
    references = np.zeros(size, dtype=np.int64)
    return (x2, L2, weights, references, W, 0, np.empty((size, n)), np.empty((size, n, n)),
            np.empty((size, 2, n, n)), value, log_value, status)


def _compiled_imported() -> bool:
    """Whether the kernels' module is imported (a ``"numba"`` call may have compiled them)."""
    return f"{__package__}.compiled" in sys.modules


def _dispatcher(name: str) -> Any:
    if name == "generalised_pair":
        from . import generalised

        return generalised.generalised_pair
    from . import compiled

    return getattr(compiled, name)


def _signature(dispatcher: Any, name: str) -> tuple:
    return tuple(dispatcher.typeof_pyval(a) for a in _arguments(name))


def _maybe_cached() -> bool:
    """Whether numba's on-disk cache may hold the kernels, checked without importing numba.

    Looks for the index file of the first kernel (``compiled.ci_pair-<line>.py<XY>.nbi``)
    where numba's cache locators put it: under ``NUMBA_CACHE_DIR`` when it is set, else in the
    ``__pycache__`` beside ``compiled.py`` or in the user-wide cache (``$XDG_CACHE_HOME/numba`` or
    ``~/.cache/numba``). A hint only: when it says yes, :func:`_load` asks numba itself
    (importing numba and initialising its target costs about 0.3-0.6 s); when it says no, the
    kernels are compiled (or loaded, if the hint missed them) in the background.
    """
    pattern = f"compiled.{KERNELS[0]}-*.py{sys.version_info[0]}{sys.version_info[1]}.nbi"
    user = os.environ.get("NUMBA_CACHE_DIR")
    if user:  # then numba uses only this directory
        places = [path for path in Path(user).glob("*") if path.is_dir()]
        return any(any(place.glob(pattern)) for place in places)
    places = [Path(__file__).resolve().parent / "__pycache__"]
    home = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    numba_home = Path(home) / "numba"
    if numba_home.is_dir():
        places.extend(path for path in numba_home.glob("*") if path.is_dir())
    return any(any(place.glob(pattern)) for place in places if place.is_dir())


def _load(name: str) -> bool:
    """Whether kernel ``name`` is compiled in this process, loading it from numba's on-disk
    cache if it is there; never compiles."""
    dispatcher = _dispatcher(name)
    signature = _signature(dispatcher, name)
    if signature in dispatcher.overloads:
        return True
    cache = getattr(dispatcher, "_cache", None)
    index = getattr(cache, "_index_path", None)
    if cache is None or (index is not None and not os.path.exists(index)):
        return False  # (before load_overload, which initialises numba's target: 0.3 s)
    result = cache.load_overload(signature, dispatcher.targetctx)
    if result is None:
        return False
    dispatcher.add_overload(result)
    return True


def ready() -> bool:
    """Whether the kernels can run now without compiling.

    True once every kernel is compiled in this process or has been loaded from numba's
    on-disk cache (checked here, in the foreground: loading takes milliseconds). Otherwise
    the first call starts the compilation once per process in a background daemon thread,
    with one :class:`cifilter.backend.CompileNotice`, and returns False (the caller keeps
    to the numpy path); later calls return False until that thread has finished.
    """
    if _state["ready"]:
        return True
    with _lock:
        if _state["ready"]:
            return True
        if _state["started"]:
            return False
        _state["started"] = True
        try:
            loaded = (_compiled_imported() or _maybe_cached()) and all(
                [_load(name) for name in KERNELS])
        except Exception:  # a cache numba cannot read: compile it in the background
            loaded = False
        if loaded:
            _state["ready"] = True
            return True
        thread = threading.Thread(target=_background, name="cifilter-compile", daemon=True)
        _state["thread"] = thread
        thread.start()
    warnings.warn("cifilter: the compiled (numba) kernels are not compiled yet; this call and "
                  "the next ones use numpy while they compile in a background thread (about "
                  "a minute or two), then the kernels take over. 'python -m cifilter compile' "
                  "compiles and caches them ahead of time.", CompileNotice,
                  stacklevel=_caller_level())
    return False


def loaded() -> bool:
    """Whether the kernels can run now, without starting a compilation or a notice.

    True when :func:`ready` is; otherwise, once per process, the kernels are loaded from
    numba's on-disk cache when the cache seems to hold them (importing numba: 0.3-0.6 s,
    once), and never compiled. For single calls under ``"auto"``, which keep to numpy
    until the kernels are there (a batched call or ``python -m cifilter compile`` puts them
    there) and do not start the background compilation themselves.
    """
    if _state["ready"]:
        return True
    if _state["started"] or _state.get("tried_loading"):
        return False
    with _lock:
        if _state["ready"] or _state["started"] or _state.get("tried_loading"):
            return bool(_state["ready"])
        _state["tried_loading"] = True
        try:
            ok = (_compiled_imported() or _maybe_cached()) and all(
                [_load(name) for name in KERNELS])
        except Exception:  # a cache numba cannot read: the single calls stay on numpy
            ok = False
        if ok:
            _state["ready"] = True
    return bool(ok)


def _caller_level() -> int:
    """The ``stacklevel`` of the first frame outside cifilter (the user's call)."""
    package = os.path.dirname(os.path.dirname(os.path.abspath(__file__))) + os.sep
    frame: Optional[FrameType] = sys._getframe(2)  # the caller of ready()
    level = 2
    while frame is not None and os.path.abspath(frame.f_code.co_filename).startswith(package):
        frame, level = frame.f_back, level + 1
    return level


def _background() -> None:
    try:
        compile_all()
    except Exception as error:  # stay on numpy; the reason is in status()
        _state["error"] = repr(error)


def compile_all(progress: Callable[[str, float, str], None] = lambda *a: None
                ) -> list[tuple[str, float, str]]:
    """Compile (or load from numba's on-disk cache) every kernel, in this thread.

    Parameters
    ----------
    progress : callable, optional
        Called as ``progress(name, seconds, how)`` after each kernel.

    Returns
    -------
    list of (str, float, str)
        Per kernel: its name, the seconds it took, and ``"compiled"``, ``"loaded from
        cache"`` or ``"already compiled"``.
    """
    done = []
    for name in KERNELS:
        start = time.perf_counter()
        dispatcher = _dispatcher(name)
        signature = _signature(dispatcher, name)
        if signature in dispatcher.overloads:
            how = "already compiled"
        else:
            how = "loaded from cache" if _load(name) else "compiled"
            if how == "compiled":
                dispatcher.compile(signature)
        seconds = time.perf_counter() - start
        done.append((name, seconds, how))
        progress(name, seconds, how)
    _state["compiled"] = done
    _state["ready"] = True
    return done


def status() -> dict[str, Any]:
    """The kernels' readiness in this process: ``ready`` (the kernels run under auto),
    ``compiling`` (the background thread runs), ``error`` (why it failed, or None) and
    ``compiled`` (what :func:`compile_all` did)."""
    thread = _state["thread"]
    return {"ready": _state["ready"], "compiling": thread is not None and thread.is_alive(),
            "error": _state["error"], "compiled": list(_state["compiled"])}


register_compiler(compile_all)
