"""Monte Carlo studies in chunks: in this process or on a Dask cluster, same numbers.

A *study* is a function ``study(rng, runs) -> dict of arrays`` that simulates ``runs``
independent runs at once (vectorised, no Python loop over runs) with the
:class:`numpy.random.Generator` it is given, and returns arrays whose first axis is the
runs. :func:`run` cuts the runs into chunks of ``chunk_size``, gives chunk ``k`` the
generator ``numpy.random.default_rng(numpy.random.SeedSequence(seed).spawn(n_chunks)[k])``,
runs the chunks (here, or on ``dask.distributed`` workers) and concatenates their results
in chunk order. The numbers therefore depend on ``seed`` and ``chunk_size`` only, never on
the number of workers or the order in which chunks finish.

Dask is optional (``pip install ".[distributed]"`` from a clone) and imported only when a cluster
is asked for.
"""

import contextlib
import math
import numbers
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple, Optional, Union

import numpy as np
from numpy.typing import NDArray

from ._progress import ProgressBar

if TYPE_CHECKING:  # Dask is optional, imported only when a cluster is asked for
    from distributed import Client

__all__ = ["DEFAULT_CHUNK_SIZE", "ChunkFailure", "MonteCarloError", "dask_client", "run"]

#: Runs per chunk when ``chunk_size`` is not given. Large enough that a vectorised study
#: spends its time in numpy rather than in per-chunk overhead (a Dask task costs about a
#: millisecond), small enough that 1 000 runs make 10 chunks to share between workers.
#: Results depend on the chunk size, so this value is part of the reproducibility contract.
DEFAULT_CHUNK_SIZE = 100

# Dask settings for the local workers of ``dask_client(workers=N)``. A chunk of a study is
# many small numpy operations; two of Dask's defaults for worker processes doubled its time
# (measured: 1.4 s against 0.6 s per chunk of the Weng reproduction, 0.6-0.8 s in process):
# the statistical profiler sampling the task's stack every 10 ms, and glibc's memory trimming
# at 64 kB (MALLOC_TRIM_THRESHOLD_), which returns freed memory to the system after nearly
# every temporary array.
_LOCAL_WORKER_CONFIG = {
    "distributed.worker.profile.enabled": False,
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
}

_INSTALL_HINT = (
    "running Monte Carlo chunks on Dask needs dask.distributed: "
    "python -m pip install \".[distributed]\" from a clone of cifilter (once published: "
    "pip install \"cifilter-fusion[distributed]\"; the PyPI project named cifilter is unrelated)"
)


class ChunkFailure(NamedTuple):
    """One chunk of a study that raised (an item of :attr:`MonteCarloError.failed`).

    The parameters are also the attributes. The chunk is re-run on its own, with the same
    numbers, by ``study(numpy.random.default_rng(failure.seed_sequence), failure.runs)``.

    Parameters
    ----------
    index : int
        The chunk's position, 0-based.
    start : int
        Its first run (runs ``start`` to ``start + runs - 1`` of the study).
    runs : int
        Its number of runs.
    seed_sequence : numpy.random.SeedSequence
        The chunk's seed: ``SeedSequence(seed).spawn(n_chunks)[index]``; its ``entropy``
        and ``spawn_key == (index,)`` identify it even when ``seed`` was None.
    error : BaseException
        What the study raised.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.montecarlo import ChunkFailure
    >>> f = ChunkFailure(2, 200, 100, np.random.SeedSequence(7).spawn(3)[2], ValueError("x"))
    >>> f.seed_sequence.spawn_key
    (2,)
    """

    # The public name shadows tuple.index (a method), which mypy reports; renaming the field
    # would break the API (failure.index, ChunkFailure(index=...)).
    index: int  # type: ignore[assignment]
    start: int
    runs: int
    seed_sequence: np.random.SeedSequence
    error: BaseException


class MonteCarloError(RuntimeError):
    """A study failed in one or more chunks; the chunks that finished are kept.

    Raised by :func:`run`, with the first failure's exception as ``__cause__``.

    Parameters
    ----------
    failed : list of ChunkFailure
        The chunks that raised, by index (at least one).
    completed : dict
        ``{chunk index: result dict}`` of every chunk that finished.
    n_chunks : int
        The number of chunks of the study.
    chunk_size : int
        Runs per chunk (the last may be smaller).
    entropy : int
        The entropy of the study's root ``SeedSequence`` (reproduces a ``seed=None`` run).

    Attributes
    ----------
    failed : list of ChunkFailure
        See above; ``failed[0].index`` and ``failed[0].seed_sequence`` name the chunk.
    completed : dict
        See above.
    partial : dict of ndarray
        The finished chunks' results concatenated in chunk order (empty if none finished).
    partial_runs : ndarray of int
        For every row of ``partial``, its run index in the whole study.
    not_run : list of int
        Chunks neither finished nor failed (in process a study stops at its first failure).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import montecarlo
    >>> def study(rng, runs):
    ...     if runs < 10:
    ...         raise ValueError("too few runs")
    ...     return {"x": rng.standard_normal(runs)}
    >>> try:
    ...     montecarlo.run(study, 25, chunk_size=10, seed=0)
    ... except montecarlo.MonteCarloError as error:
    ...     print(error.failed[0].index, error.partial["x"].shape, error.partial_runs[-1])
    2 (20,) 19
    """

    def __init__(self, failed: Sequence[ChunkFailure],
                 completed: Mapping[int, Mapping[str, np.ndarray]], n_chunks: int,
                 chunk_size: int, entropy: Union[int, Sequence[int]]) -> None:
        self.failed = sorted(failed, key=lambda failure: failure.index)
        self.completed = dict(sorted(completed.items()))
        self.n_chunks = n_chunks
        self.entropy = entropy
        self.partial = _concatenate(list(self.completed.values()))
        done = {failure.index for failure in self.failed} | set(self.completed)
        self.not_run = [k for k in range(n_chunks) if k not in done]
        self.partial_runs = np.concatenate(
            [k * chunk_size + np.arange(len(next(iter(result.values()), ())))
             for k, result in self.completed.items()] or [np.zeros(0, dtype=int)])
        first = self.failed[0]
        super().__init__(
            f"Monte Carlo chunk {first.index} of {n_chunks} (runs {first.start}.."
            f"{first.start + first.runs - 1}; seed: SeedSequence(entropy={entropy}, "
            f"spawn_key={first.seed_sequence.spawn_key})) failed with "
            f"{type(first.error).__name__}: {first.error}"
            + (f"; {len(self.failed) - 1} more chunk(s) failed" if len(self.failed) > 1 else "")
            + f"; {len(self.completed)} finished chunk(s) kept in .partial")


def _check_positive_int(value, name):
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return int(value)


def _root_seed_sequence(seed):
    if seed is None or (isinstance(seed, numbers.Integral) and not isinstance(seed, bool)):
        if seed is not None and seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed}")
        return np.random.SeedSequence(seed)
    if isinstance(seed, np.random.SeedSequence):
        return seed
    if isinstance(seed, np.random.Generator):
        # Entropy drawn from the caller's generator: reproducible from its state.
        return np.random.SeedSequence(seed.integers(0, 2**32, size=4, dtype=np.uint64))
    raise TypeError("seed must be a non-negative integer, a numpy.random.SeedSequence, "
                    f"a numpy.random.Generator or None, got {type(seed).__name__}")


def _chunks(runs, chunk_size, root):
    """``(index, start, size, seed_sequence)`` of every chunk."""
    n_chunks = math.ceil(runs / chunk_size)
    children = root.spawn(n_chunks)
    return [(k, k * chunk_size, min(chunk_size, runs - k * chunk_size), children[k])
            for k in range(n_chunks)]


def _run_chunk(study, seed_sequence, runs):
    """One chunk (also what a Dask worker executes): the study's checked result."""
    result = study(np.random.default_rng(seed_sequence), runs)
    return _check_result(result, runs, study)


def _study_name(study):
    """The progress bar's label: the study's ``__name__`` (for a partial, its function's)."""
    name = getattr(study, "__name__", None)
    if name is None:
        inner = getattr(study, "func", study)  # functools.partial
        name = getattr(inner, "__name__", type(inner).__name__)
    return name


def _check_result(result, runs, study):
    name = _study_name(study)
    if not isinstance(result, dict):
        raise TypeError(f"study {name!r} must return a dict of arrays, "
                        f"got {type(result).__name__}")
    checked = {}
    for key, value in result.items():
        array = np.asarray(value)
        if array.ndim == 0 or array.shape[0] != runs:
            raise ValueError(
                f"study {name!r} returned {key!r} of shape {array.shape}; every array's "
                f"first axis must be the {runs} runs of the chunk")
        checked[key] = array
    return checked


def _concatenate(results):
    if not results:
        return {}
    keys = list(results[0])
    for k, result in enumerate(results):
        if list(result) != keys:
            raise ValueError(f"study returned keys {sorted(result)} in chunk {k} but "
                             f"{sorted(keys)} in chunk 0")
    return {key: np.concatenate([result[key] for result in results], axis=0) for key in keys}


def run(study: Callable[[np.random.Generator, int], dict[str, Any]], runs: int, *,
        chunk_size: Optional[int] = None, client: Optional[Union["Client", str]] = None,
        seed: Optional[Union[int, np.random.SeedSequence, np.random.Generator]] = None,
        progress: Optional[bool] = None) -> dict[str, NDArray[Any]]:
    """Run a vectorised Monte Carlo study in seeded chunks, here or on Dask.

    Chunk ``k`` (runs ``k * chunk_size`` onwards) is simulated by
    ``study(numpy.random.default_rng(SeedSequence(seed).spawn(n_chunks)[k]), size_k)``, so
    that for a given ``seed`` and ``chunk_size`` the result is bit-identical in process and
    on any number of Dask workers.

    Parameters
    ----------
    study : callable
        ``study(rng, runs) -> dict`` of arrays whose first axis has length ``runs``;
        ``rng`` is a :class:`numpy.random.Generator`, the study's only source of
        randomness. On Dask the study is pickled (cloudpickle): a module-level function or
        a :func:`functools.partial` of one works everywhere.
    runs : int
        Total number of runs, >= 1.
    chunk_size : int, optional
        Runs per chunk (the last chunk may be smaller); default :data:`DEFAULT_CHUNK_SIZE`.
        The numbers depend on it, not on the workers.
    client : dask.distributed.Client or str, optional
        ``None`` (default) runs the chunks one after the other in this process; a
        ``Client`` runs them on its cluster; a string is a scheduler address
        (``"tcp://host:8786"``) to connect to for the duration of the call (within Dask's
        connect timeout, ``distributed.comm.timeouts.connect``, else :class:`TimeoutError`;
        see :func:`dask_client`).
    seed : int, numpy.random.SeedSequence, numpy.random.Generator or None, optional
        The root of the chunks' seeds. ``None`` draws fresh entropy (recorded in a
        :class:`MonteCarloError`); a Generator contributes entropy drawn from it.
    progress : bool or None, optional
        ``True`` draws a progress bar on stderr, ``False`` never; ``None`` (default) draws
        it only when stderr is a terminal and the study has run for more than 2 s. The bar
        is labelled with the study's ``__name__`` (a partial's function's, unless the
        partial is given a ``__name__``).

    Returns
    -------
    dict of ndarray
        The study's arrays, concatenated over the chunks along the first axis (``runs``
        rows), keys in the order the study returns them.

    Raises
    ------
    MonteCarloError
        If the study raises in a chunk: the message names the chunk index, its runs and
        its seed (``SeedSequence(entropy, spawn_key=(k,))``); ``.partial`` holds the
        finished chunks. In process the study stops at the first failing chunk (the rest
        are listed in ``.not_run``); on Dask, where all chunks are submitted at once,
        every chunk runs to its end and all failures are listed.
    TypeError
        If ``study`` is not callable, ``runs``/``chunk_size`` are not integers, ``seed``
        or ``client`` or ``progress`` has the wrong type, or the study returns something
        other than a dict (reported through :class:`MonteCarloError`).
    ValueError
        If ``runs`` or ``chunk_size`` is < 1 or ``seed`` is negative.
    TimeoutError
        If ``client`` is an address whose scheduler does not answer within Dask's connect
        timeout.
    ImportError
        If ``client`` is given and ``dask.distributed`` is not installed.

    See Also
    --------
    dask_client : a local cluster or a connection for the command line's ``--workers`` and
        ``--scheduler``.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter import montecarlo
    >>> def study(rng, runs):
    ...     errors = rng.standard_normal((runs, 2))
    ...     return {"nees": np.sum(errors**2, axis=1)}
    >>> result = montecarlo.run(study, 1000, chunk_size=250, seed=1)
    >>> result["nees"].shape
    (1000,)
    >>> bool(abs(result["nees"].mean() - 2.0) < 0.2)  # chi-square(2) mean
    True

    On a cluster (same numbers): ``montecarlo.run(study, 1000, chunk_size=250, seed=1,
    client=client)`` with ``client = dask.distributed.Client(...)``.
    """
    if not callable(study):
        raise TypeError(f"study must be callable, got {type(study).__name__}")
    runs = _check_positive_int(runs, "runs")
    chunk_size = (DEFAULT_CHUNK_SIZE if chunk_size is None
                  else _check_positive_int(chunk_size, "chunk_size"))
    if progress is not None and not isinstance(progress, bool):
        raise TypeError(f"progress must be True, False or None, got {type(progress).__name__}")
    root = _root_seed_sequence(seed)
    chunks = _chunks(runs, chunk_size, root)
    bar = ProgressBar(runs, label=_study_name(study), enabled=progress)
    with bar:
        if client is None:
            completed, failed = _run_here(study, chunks, bar)
        else:
            with _as_client(client) as dask_client_:
                completed, failed = _run_on_dask(study, chunks, bar, dask_client_)
    if failed:
        error = MonteCarloError(failed, completed, len(chunks), chunk_size, root.entropy)
        raise error from failed[0].error
    return _concatenate([completed[k] for k in range(len(chunks))])


def _run_here(study, chunks, bar):
    completed = {}
    for index, start, size, seed_sequence in chunks:
        try:
            completed[index] = _run_chunk(study, seed_sequence, size)
        except Exception as error:  # any failure of user code is reported with its seed
            return completed, [ChunkFailure(index, start, size, seed_sequence, error)]
        bar.update(size)
    return completed, []


def _import_distributed():
    try:
        import distributed
    except ImportError as error:
        raise ImportError(_INSTALL_HINT) from error
    return distributed


def _check_timeout(timeout):
    if isinstance(timeout, bool) or not isinstance(timeout, numbers.Real):
        raise TypeError(f"timeout must be a number of seconds, got {type(timeout).__name__}")
    if not (math.isfinite(timeout) and timeout > 0):
        raise ValueError(f"timeout must be a positive number of seconds, got {timeout}")
    return float(timeout)


def _connect_timeout(distributed, timeout):
    """Seconds to wait for a scheduler: ``timeout``, or Dask's connect timeout
    (``distributed.comm.timeouts.connect``, 30 s unless configured)."""
    if timeout is None:
        import dask
        from dask.utils import parse_timedelta

        timeout = parse_timedelta(
            dask.config.get("distributed.comm.timeouts.connect"), default="seconds")
    return _check_timeout(timeout)


def _check_scheduler_answers(distributed, address, timeout):
    """Open a connection to ``address`` and complete Dask's handshake within ``timeout``
    seconds, else raise :class:`TimeoutError`.

    ``distributed.Client`` bounds the TCP connection by its timeout but then waits for the
    scheduler's handshake without one, so an address that accepts connections and never
    answers (a port held by another program, a wedged scheduler) made it wait forever. The
    probe runs in a thread of its own (with its own event loop, so it also works where the
    caller's thread runs one, as in a notebook) and is given up after ``timeout``.
    """
    import asyncio

    outcome = {}  # what the probe raised

    async def probe():
        comm = await distributed.comm.connect(address, timeout=timeout)
        await comm.close()

    def target():
        try:
            asyncio.run(asyncio.wait_for(probe(), timeout))
        except BaseException as error:  # reported to the caller's thread below
            outcome["error"] = error

    thread = threading.Thread(target=target, name="cifilter-scheduler-probe", daemon=True)
    thread.start()
    thread.join(timeout + 1.0)
    error = outcome.get("error")
    if thread.is_alive() or isinstance(error, (TimeoutError, asyncio.TimeoutError)):
        raise TimeoutError(f"the Dask scheduler at {address!r} accepted the connection but "
                           f"did not answer within {timeout:g} s")
    if error is not None:
        raise error


def _connect(distributed, address, timeout):
    """A Client connected to the scheduler at ``address``, within ``timeout`` seconds."""
    timeout = _connect_timeout(distributed, timeout)
    _check_scheduler_answers(distributed, address, timeout)
    return distributed.Client(address, set_as_default=False, timeout=timeout)


@contextlib.contextmanager
def _as_client(client):
    """The given Client, or a connection to a scheduler address closed on exit."""
    distributed = _import_distributed()
    if isinstance(client, str):
        connection = _connect(distributed, client, None)
        try:
            yield connection
        finally:
            connection.close()
    elif isinstance(client, distributed.Client):
        yield client
    else:
        raise TypeError("client must be a dask.distributed.Client, a scheduler address "
                        f"string or None, got {type(client).__name__}")


def _run_on_dask(study, chunks, bar, client):
    distributed = _import_distributed()
    futures = {
        client.submit(_run_chunk, study, seed_sequence, size, pure=False):
            (index, start, size, seed_sequence)
        for index, start, size, seed_sequence in chunks
    }
    completed, failed = {}, []
    try:
        for future in distributed.as_completed(list(futures), loop=client.loop):
            index, start, size, seed_sequence = futures[future]
            result, error = _settle(future)
            if error is None:
                completed[index] = result
                bar.update(size)
                continue
            failed.append(ChunkFailure(index, start, size, seed_sequence, error))
    finally:  # only on an interruption (e.g. Ctrl-C) are there unfinished chunks
        client.cancel([f for f in futures if not f.done()])
    return completed, failed


def _settle(future):
    """``(result, None)`` of a chunk's future, or ``(None, error)``.

    The status a future had when :func:`distributed.as_completed` yielded it is not
    final: when a worker process dies, the results it held are lost and recomputed
    elsewhere, so a chunk that had finished can be ``"lost"`` or ``"pending"`` for a while.
    ``result()`` waits until it settles: the chunk's result, or what it raised (the study's
    exception; ``KilledWorker`` for a chunk whose workers kept dying; a cancellation).
    """
    import concurrent.futures

    try:
        return future.result(), None
    except (Exception, concurrent.futures.CancelledError) as error:
        return None, error


@contextlib.contextmanager
def dask_client(workers: Optional[int] = None, scheduler: Optional[str] = None, *,
                timeout: Optional[float] = None) -> Iterator[Optional["Client"]]:
    """The Dask client for ``--workers N`` or ``--scheduler ADDRESS``, or None for neither.

    ``workers`` starts a :class:`distributed.LocalCluster` of that many worker processes
    with one thread each (a chunk is numpy code that holds the GIL much of the time, so
    processes rather than threads share the cores; the dashboard gets a free port), with
    Dask's worker profiler off and without its 64 kB ``MALLOC_TRIM_THRESHOLD_`` (together
    they doubled the time of a chunk of small numpy operations); it is shut down on exit.
    ``scheduler`` connects to an existing cluster (left running on exit; its workers keep
    their own configuration); an address that does not answer within ``timeout`` is an
    error, also when it accepts the connection and then stays silent (Dask's own client
    would wait for its handshake forever).

    Parameters
    ----------
    workers : int, optional
        Number of local worker processes, >= 1.
    scheduler : str, optional
        Address of a running Dask scheduler, e.g. ``"tcp://10.0.0.5:8786"``.
    timeout : float, optional
        Seconds to wait for the scheduler to connect and answer (keyword only); default
        Dask's connect timeout, ``distributed.comm.timeouts.connect`` (30 s unless
        configured). Also used as the client's timeout.

    Yields
    ------
    dask.distributed.Client or None
        Pass it to :func:`run` as ``client``; None when neither argument is given (the
        study then runs in this process).

    Raises
    ------
    ValueError
        If both are given, ``workers < 1``, ``scheduler`` is empty or ``timeout`` is not
        positive.
    TypeError
        If ``workers`` is not an integer, ``scheduler`` not a string or ``timeout`` not a
        number.
    TimeoutError
        If the scheduler does not connect and answer within ``timeout`` (an
        :class:`OSError`, as are the errors of an address that refuses the connection).
    ImportError
        If a cluster is asked for and ``dask.distributed`` is not installed.

    Examples
    --------
    >>> from cifilter import montecarlo
    >>> with montecarlo.dask_client() as client:  # neither: run in process
    ...     print(client)
    None

    With ``montecarlo.dask_client(workers=2) as client:`` the same ``run`` calls use two
    local worker processes.
    """
    if workers is not None and scheduler is not None:
        raise ValueError("give either workers or scheduler, not both")
    if workers is not None:
        workers = _check_positive_int(workers, "workers")
    if scheduler is not None:
        if not isinstance(scheduler, str):
            raise TypeError(f"scheduler must be an address string, got {type(scheduler).__name__}")
        if not scheduler.strip():
            raise ValueError("scheduler must be a non-empty address")
    if timeout is not None:
        timeout = _check_timeout(timeout)
    if workers is None and scheduler is None:
        yield None
        return
    distributed = _import_distributed()
    if scheduler is not None:
        client = _connect(distributed, scheduler, timeout)
        try:
            yield client
        finally:
            client.close()
        return
    import dask

    with dask.config.set(_LOCAL_WORKER_CONFIG):  # read by the workers when they start
        cluster = distributed.LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    try:
        client = distributed.Client(cluster, set_as_default=False)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()

