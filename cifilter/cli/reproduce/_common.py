"""Command-line pieces shared by the reproductions: argument types, the Monte Carlo runner.

Every reproduction's Monte Carlo goes through :func:`cifilter.montecarlo.run`, with a seed
derived from ``--seed`` and a fixed key per study, so that a study's numbers depend on
the seed, its sizes and its chunk size only: not on ``--workers``/``--scheduler``, nor on
which other sections run.
"""

import argparse
import functools
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any, Optional, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ... import montecarlo
from ..args import add_parallel_arguments, plot_directory
from ..args import seed as seed_argument

if TYPE_CHECKING:  # Dask is optional, imported only when a cluster is asked for
    from distributed import Client

__all__ = []


def add_common_arguments(parser: argparse.ArgumentParser, plot_help: str) -> None:
    """``--seed``, ``--plot DIR`` and ``--workers``/``--scheduler``."""
    parser.add_argument("--seed", type=seed_argument, default=0,
                        help="random seed, >= 0 (default 0)")
    parser.add_argument("--plot", metavar="DIR", type=plot_directory, help=plot_help)
    add_parallel_arguments(parser)


def parallel_client(args: argparse.Namespace) -> AbstractContextManager[Optional["Client"]]:
    """The Dask client for ``args.workers``/``args.scheduler`` (None: in process)."""
    return montecarlo.dask_client(workers=getattr(args, "workers", None),
                                  scheduler=getattr(args, "scheduler", None))


def run_study(study: Callable[..., dict[Any, ArrayLike]], label: str, runs: int, seed: int,
              key: int, client: Optional[Union["Client", str]],
              chunk_size: Optional[int] = None,
              **options: Any) -> dict[Any, NDArray[Any]]:
    """``montecarlo.run`` of ``study(rng, runs, **options)`` with the progress label ``label``.

    The seed is ``SeedSequence(seed, spawn_key=(key,))``: one independent stream per
    study of a reproduction, whatever else runs.
    """
    bound = functools.partial(study, **options)
    # the progress bar's label (a partial takes attributes; typeshed declares none)
    bound.__name__ = label  # type: ignore[attr-defined]
    return montecarlo.run(bound, runs, chunk_size=chunk_size, client=client,
                          seed=np.random.SeedSequence(seed, spawn_key=(key,)))
