"""Decentralised tracking over a graph, vectorised over Monte Carlo runs and nodes.

Every step each node predicts with the target model, updates with its own measurement,
then (every ``period`` steps) receives its neighbours' estimates and fuses them with the
chosen rule, writing the result back into its filter (``feedback=True``). The fused
estimate then travels on at the next exchange: the information a node receives comes back
to it through its neighbours, and a rule that assumes independent errors counts it again
(data incest).

Arrays have the runs as the first axis and the nodes as the next; the filters of all runs
and nodes are updated together, and each fusion is one call of :func:`cifilter.fuse` on
the stacked estimates of every (run, node) pair with the same number of received messages
(all at once) or of every pair fusing a message in a given neighbour slot (sequential). The
Python loops are over time steps, sensor groups and neighbour slots only.

Because every rule returns its gains (``x = sum_i K_i x_i``), the simulation also
propagates the true joint error covariance of all nodes (a linear recursion in the
filter gains and fusion gains of each run); a rule whose registry record has a
``truth_options`` hook (``"optimal"``: the joint covariance; ``"pci"``: the correlation
bound it implies) gets the joint covariance of the estimates it fuses.
"""

import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Optional, Union

import numpy as np
from numpy.typing import NDArray

from .._numerics.linalg import cholesky
from .._numerics.validation import as_rng, check_int, check_scalar
from ..registry import fuse, get_method
from .graph import Scenario

__all__ = ["NetworkData", "NetworkTrack", "centralised", "run_network", "simulate_data"]


@dataclass(frozen=True)
class NetworkData:
    """Simulated truth, measurements, initial estimates and delivered messages.

    The parameters are also the attributes. One :class:`NetworkData` is shared by every
    rule compared, so that they see the same target, noises and packet losses.

    Parameters
    ----------
    truth : ndarray, shape (runs, steps, n)
        True states at steps ``1..steps``.
    measurements : tuple of ndarray, shapes (runs, steps, m_i)
        Measurements of each node.
    initial : ndarray, shape (runs, nodes, n)
        Initial estimates of the nodes' filters (their errors are independent).
    delivered : ndarray of bool, shape (runs, steps, nodes, nodes), or None
        ``delivered[r, k, i, j]``: node ``i`` receives node ``j``'s estimate at step ``k``
        if they are linked (None: every message arrives).

    Examples
    --------
    >>> from cifilter.network import ring, simulate_data
    >>> data = simulate_data(ring(4), runs=3, steps=5, rng=0)
    >>> data.truth.shape, data.initial.shape, data.delivered is None
    ((3, 5, 4), (3, 4, 4), True)
    """

    truth: NDArray[np.float64]
    measurements: tuple[NDArray[np.float64], ...]
    initial: NDArray[np.float64]
    delivered: Optional[NDArray[np.bool_]] = None

    @property
    def runs(self) -> int:
        """Number of Monte Carlo runs.

        Returns
        -------
        int
            Length of the first axis.

        Examples
        --------
        >>> from cifilter.network import ring, simulate_data
        >>> simulate_data(ring(3), runs=2, steps=4, rng=0).runs
        2
        """
        return self.truth.shape[0]

    @property
    def steps(self) -> int:
        """Number of time steps.

        Returns
        -------
        int
            Length of the second axis.

        Examples
        --------
        >>> from cifilter.network import ring, simulate_data
        >>> simulate_data(ring(3), runs=2, steps=4, rng=0).steps
        4
        """
        return self.truth.shape[1]


def simulate_data(scenario: Scenario, runs: int, steps: int, *, loss: float = 0.0,
                  rng: Optional[Union[int, np.random.Generator]] = None) -> NetworkData:
    """Simulate the target, the measurements, the initial estimates and the packet losses.

    Parameters
    ----------
    scenario : Scenario
        The network and its models.
    runs, steps : int
        Monte Carlo runs and time steps.
    loss : float, optional
        Probability that a message between linked nodes is lost, independently per
        message, direction and step (default 0).
    rng : numpy.random.Generator, int or None, optional
        Randomness (the only source; same seed, same data).

    Returns
    -------
    NetworkData
        The data, drawn in this order: initial errors, process noises, each node's
        measurement noises, losses.

    Raises
    ------
    ValueError
        If ``runs`` or ``steps`` is below 1 or ``loss`` is outside [0, 1].

    Examples
    --------
    >>> from cifilter.network import naveen_taylor, simulate_data
    >>> data = simulate_data(naveen_taylor(), runs=2, steps=3, loss=0.2, rng=1)
    >>> data.delivered.shape, [z.shape for z in data.measurements][:2]
    ((2, 3, 6, 6), [(2, 3, 2), (2, 3, 2)])
    """
    if not isinstance(scenario, Scenario):
        raise TypeError(f"scenario must be a Scenario, got {type(scenario).__name__}")
    runs, steps = check_int(runs, "runs", low=1), check_int(steps, "steps", low=1)
    loss = check_scalar(loss, "loss", low=0, high=1)
    rng = as_rng(rng)
    n, nodes = scenario.dim, scenario.nodes
    initial = scenario.x0 + np.einsum("mij,rmj->rmi", cholesky(scenario.P0, "P0"),
                                      rng.standard_normal((runs, nodes, n)))
    # Q may be singular (no noise on some components): its square root by eigenvalues
    w, V = np.linalg.eigh(scenario.Q)
    root_Q = V * np.sqrt(np.clip(w, 0.0, None))
    noise = rng.standard_normal((runs, steps, n)) @ root_Q.T
    truth = np.empty((runs, steps, n))
    state = np.broadcast_to(scenario.x0, (runs, n))
    for k in range(steps):
        state = state @ scenario.F.T + noise[:, k]
        truth[:, k] = state
    measurements = []
    for H, R in zip(scenario.H, scenario.R):
        v = rng.standard_normal((runs, steps, H.shape[0])) @ cholesky(R, "R").T
        measurements.append(truth @ H.T + v)
    delivered = None
    if loss > 0:
        delivered = rng.random((runs, steps, nodes, nodes)) >= loss
    return NetworkData(truth, tuple(measurements), initial, delivered)


@dataclass(frozen=True)
class NetworkTrack:
    """The nodes' estimates over time under one rule (returned by :func:`run_network`).

    The parameters are also the attributes.

    Parameters
    ----------
    method : str
        The rule, ``"local"`` (no exchange) or ``"centralised"``.
    x : ndarray, shape (runs, steps, nodes, n)
        Each node's estimate after the step's exchange (the fused estimate where it fused).
    P : ndarray, shape (runs, steps, nodes, n, n)
        Their covariances.
    fuse_seconds : float
        Wall time spent in the fusion calls.
    fusions : int
        Number of node fusions performed (over all runs, nodes and steps).
    exchanges : int
        Number of time steps with an exchange.

    Examples
    --------
    >>> from cifilter.network import ring, run_network, simulate_data
    >>> scenario = ring(4)
    >>> track = run_network(scenario, simulate_data(scenario, 2, 5, rng=0), "ci")
    >>> track.x.shape, track.fusions
    ((2, 5, 4, 4), 40)
    """

    method: str
    x: NDArray[np.float64]
    P: NDArray[np.float64]
    fuse_seconds: float = 0.0
    fusions: int = 0
    exchanges: int = 0


def _kron_eye(nodes, A):
    """``blockdiag(A, ..., A)`` of ``nodes`` blocks."""
    return np.kron(np.eye(nodes), A)


def _predict(x, P, F, Q):
    return x @ F.T, F @ P @ F.T + Q


def _sensor_groups(scenario):
    """Nodes grouped by measurement dimension: (indices, H stack, R stack)."""
    groups = {}
    for i, H in enumerate(scenario.H):
        groups.setdefault(H.shape[0], []).append(i)
    return [(np.array(idx), np.stack([scenario.H[i] for i in idx]),
             np.stack([scenario.R[i] for i in idx])) for idx in groups.values()]


def _update(x, P, z, H, R):
    """Kalman update of stacked filters (Joseph form); returns x, P, I - K H and K R K^T."""
    PHt = P @ np.swapaxes(H, -1, -2)
    S = H @ PHt + R
    L = np.linalg.cholesky(S)
    # K = P H^T S^-1 through the Cholesky factor of S (S is symmetric positive definite)
    K = np.swapaxes(np.linalg.solve(np.swapaxes(L, -1, -2),
                                    np.linalg.solve(L, np.swapaxes(PHt, -1, -2))), -1, -2)
    innovation = z - np.einsum("...ij,...j->...i", H, x)
    x = x + np.einsum("...ij,...j->...i", K, innovation)
    A = np.eye(x.shape[-1]) - K @ H
    KRK = K @ R @ np.swapaxes(K, -1, -2)
    P = A @ P @ np.swapaxes(A, -1, -2) + KRK
    return x, 0.5 * (P + np.swapaxes(P, -1, -2)), A, KRK


def _block_diagonal(blocks):
    """(runs, nodes, n, n) blocks -> (runs, nodes*n, nodes*n) block-diagonal matrices."""
    runs, nodes, n, _ = blocks.shape
    out = np.zeros((runs, nodes, n, nodes, n))
    index = np.arange(nodes)
    out[:, index, :, index, :] = np.moveaxis(blocks, 1, 0)
    return out.reshape(runs, nodes * n, nodes * n)


def _check_config(period, sequential, delay, feedback):
    period = check_int(period, "period", low=1)
    for name, value in (("sequential", sequential), ("delay", delay), ("feedback", feedback)):
        if not isinstance(value, (bool, np.bool_)):
            raise TypeError(f"{name} must be True or False, got {value!r}")
    return period


def run_network(scenario: Scenario, data: NetworkData, method: Optional[str] = "ci", *,
                feedback: bool = True, period: int = 1, sequential: bool = False,
                delay: bool = False, rng: Optional[Union[int, np.random.Generator]] = None,
                options: Optional[Mapping[str, Any]] = None) -> NetworkTrack:
    """Run the decentralised network with one fusion rule over all runs at once.

    Parameters
    ----------
    scenario : Scenario
        The network and its models.
    data : NetworkData
        Truth, measurements, initial estimates and delivered messages
        (:func:`simulate_data`).
    method : str or None, optional
        A registered rule (:func:`cifilter.available_methods`), or None for local filters
        that never exchange. Default ``"ci"``.
    feedback : bool, optional
        Write the fused estimate back into the node's filter (default True). False keeps
        each filter local and reports the fused estimate only (no data incest).
    period : int, optional
        Exchange every ``period`` steps (default 1: every step).
    sequential : bool, optional
        Fuse the received estimates one at a time, in the order of the neighbours'
        indices, each into the result of the previous fusion (two estimates per call);
        default False fuses the node's own estimate and all received ones in one call.
    delay : bool, optional
        Messages arrive one step late: a node fuses its neighbours' estimates of the
        previous step, brought to the current time by the target model (their predicted
        estimates, before their own update). Default False.
    rng : numpy.random.Generator, int or None, optional
        Randomness for rules that sample (given to the rule's ``truth_options`` hook).
    options : mapping, optional
        Options of the rule (for instance ``{"criterion": "det"}``).

    Returns
    -------
    NetworkTrack
        Every node's estimate and covariance at every step of every run, the time spent
        fusing and the number of fusions.

    Raises
    ------
    ValueError
        Unknown method, data that does not fit the scenario, or what the rule raises
        (for instance a truth hook that cannot handle more than two estimates).
    TypeError
        Bad option types.

    Examples
    --------
    >>> from cifilter.network import naveen_taylor, run_network, simulate_data
    >>> scenario = naveen_taylor()
    >>> data = simulate_data(scenario, runs=3, steps=10, rng=0)
    >>> ci = run_network(scenario, data, "ci")
    >>> local = run_network(scenario, data, None)
    >>> bool((ci.P[:, -1].trace(axis1=-2, axis2=-1)
    ...       < local.P[:, -1].trace(axis1=-2, axis2=-1)).all())
    True
    """
    period = _check_config(period, sequential, delay, feedback)
    record = None if method is None else get_method(method)
    options = dict(options or {})
    rng = as_rng(rng)
    n, nodes = scenario.dim, scenario.nodes
    runs, steps = data.runs, data.steps
    if data.initial.shape != (runs, nodes, n):
        raise ValueError(f"data.initial must have shape {(runs, nodes, n)} for this scenario, "
                         f"got {data.initial.shape}")
    if len(data.measurements) != nodes:
        raise ValueError(f"data has measurements of {len(data.measurements)} nodes, the "
                         f"scenario {nodes}")
    need_joint = record is not None and record.truth_options is not None
    groups = _sensor_groups(scenario)
    measurements = [np.stack([data.measurements[i] for i in idx], axis=2)
                    for idx, _, _ in groups]
    big_F = _kron_eye(nodes, scenario.F)
    big_Q = np.kron(np.ones((nodes, nodes)), scenario.Q)  # the process noise is common

    x = data.initial.copy()
    P = np.broadcast_to(scenario.P0, (runs, nodes, n, n)).copy()
    joint = _block_diagonal(P) if need_joint else None
    out_x, out_P = np.empty((runs, steps, nodes, n)), np.empty((runs, steps, nodes, n, n))
    seconds, fusions, exchanges = 0.0, 0, 0
    for k in range(steps):
        x, P = _predict(x, P, scenario.F, scenario.Q)
        if need_joint:
            joint = big_F @ joint @ big_F.T + big_Q
        x_prior, P_prior, joint_prior = x, P, joint
        x, P = x.copy(), P.copy()
        # arrays when need_joint, else None (Any: mypy cannot tie them to need_joint)
        A_blocks: Any = np.empty((runs, nodes, n, n)) if need_joint else None
        KRK_blocks: Any = np.empty((runs, nodes, n, n)) if need_joint else None
        for (idx, H, R), z in zip(groups, measurements):
            x[:, idx], P[:, idx], A, KRK = _update(x[:, idx], P[:, idx], z[:, k], H, R)
            if need_joint:
                A_blocks[:, idx], KRK_blocks[:, idx] = A, KRK
        if need_joint:
            A_big = _block_diagonal(A_blocks)
            joint = A_big @ joint_prior @ np.swapaxes(A_big, -1, -2) \
                + _block_diagonal(KRK_blocks)
        if record is None or (k + 1) % period:
            out_x[:, k], out_P[:, k] = x, P
            continue
        exchanges += 1
        received = np.broadcast_to(scenario.adjacency, (runs, nodes, nodes))
        if data.delivered is not None:
            received = received & data.delivered[:, k]
        if delay:
            messages_x, messages_P = x_prior, P_prior
            base = None
            if need_joint:  # base errors: [updated of every node, predicted of every node]
                cross = A_big @ joint_prior
                base = np.block([[joint, cross], [np.swapaxes(cross, -1, -2), joint_prior]])
            offset = nodes
        else:
            messages_x, messages_P, base, offset = x, P, joint, 0
        start = time.perf_counter()
        fused_x, fused_P, maps, count = _exchange(
            record, x, P, messages_x, messages_P, received, offset, base, sequential,
            rng, options, n)
        seconds += time.perf_counter() - start
        fusions += count
        out_x[:, k], out_P[:, k] = fused_x, fused_P
        if feedback:
            x, P = fused_x, fused_P
            if need_joint:
                flat = maps.reshape(runs, nodes * n, -1)
                joint = flat @ base @ np.swapaxes(flat, -1, -2)
                joint = 0.5 * (joint + np.swapaxes(joint, -1, -2))
    name = "local" if record is None else record.name
    return NetworkTrack(name, out_x, out_P, seconds, fusions, exchanges)


def _exchange(record, x, P, messages_x, messages_P, received, offset, base, sequential, rng,
              options, n):
    """Fuse every node's estimate with its received messages (one step, all runs).

    Returns the fused means and covariances, the maps ``M`` (runs, nodes, n, B n) of the
    fused errors as linear functions of the base errors (when ``base``, the joint
    covariance of the base errors, is given), and the number of fusions.
    """
    runs, nodes = x.shape[:2]
    fused_x, fused_P = x.copy(), P.copy()
    maps = None
    if base is not None:
        maps = np.zeros((runs, nodes, n, base.shape[-1]))
        eye = np.eye(n)
        for i in range(nodes):
            maps[:, i, :, i * n:(i + 1) * n] = eye
    count = 0
    if sequential:
        # slot s of node i: the s-th message it received, in the order of the senders
        order = np.cumsum(received, axis=-1) - 1
        for s in range(received.shape[-1]):
            r_idx, i_idx, j_idx = np.nonzero(received & (order == s))
            if r_idx.size == 0:
                break
            count += _fuse_groups(record, [(r_idx, i_idx, j_idx[:, None])], fused_x, fused_P,
                                  messages_x, messages_P, maps, offset, base, rng, options, n)
        return fused_x, fused_P, maps, count
    counts = received.sum(axis=-1)
    groups = []
    for c in np.unique(counts[counts > 0]):
        r_idx, i_idx = np.nonzero(counts == c)
        j_idx = np.nonzero(received[r_idx, i_idx])[1].reshape(-1, c)
        groups.append((r_idx, i_idx, j_idx))
    count += _fuse_groups(record, groups, fused_x, fused_P, messages_x, messages_P, maps,
                          offset, base, rng, options, n)
    return fused_x, fused_P, maps, count


def _fuse_groups(record, groups, fused_x, fused_P, messages_x, messages_P, maps, offset,
                 base, rng, options, n):
    """Fuse each group (runs r, nodes i, received j (B, c)) in one call; in place."""
    count = 0
    for r_idx, i_idx, j_idx in groups:
        c = j_idx.shape[1]
        xs = np.concatenate([fused_x[r_idx, i_idx][:, None], messages_x[r_idx[:, None], j_idx]],
                            axis=1)
        Ps = np.concatenate([fused_P[r_idx, i_idx][:, None],
                             messages_P[r_idx[:, None], j_idx]], axis=1)
        call_options = dict(options)
        rows = None
        if base is not None:
            size = base.shape[-1]
            rows = np.zeros((r_idx.size, c + 1, n, size))
            rows[:, 0] = maps[r_idx, i_idx]
            columns = (offset + j_idx)[..., None] * n + np.arange(n)  # (B, c, n)
            batch = np.arange(r_idx.size)[:, None, None]
            slot = np.arange(1, c + 1)[None, :, None]
            rows[batch, slot, np.arange(n)[None, None, :], columns] = 1.0
            flat = rows.reshape(r_idx.size, (c + 1) * n, size)
            joint = flat @ base[r_idx] @ np.swapaxes(flat, -1, -2)
            joint = 0.5 * (joint + np.swapaxes(joint, -1, -2))
            call_options.update(record.options_given_truth(joint, rng, count=c + 1))
        result = fuse([(xs[:, s], Ps[:, s]) for s in range(c + 1)], method=record.name,
                      **call_options)
        fused_x[r_idx, i_idx] = np.asarray(result.x).reshape(r_idx.size, n)
        fused_P[r_idx, i_idx] = result.P
        if rows is not None:
            if result.gains is None:
                raise ValueError(
                    f"rule {record.name!r} returns no gains: the joint covariance its truth "
                    "hook needs cannot be propagated")
            gains = np.broadcast_to(result.gains, (r_idx.size, c + 1, n, n))
            maps[r_idx, i_idx] = np.einsum("bsij,bsjk->bik", gains, rows)
        count += r_idx.size
    return count


def centralised(scenario: Scenario, data: NetworkData) -> NetworkTrack:
    """The centralised Kalman filter: one filter with every node's measurement.

    It starts from the fusion of the nodes' independent priors and is the best any
    decentralised network can do (the reference of the comparisons).

    Parameters
    ----------
    scenario : Scenario
        The network and its models.
    data : NetworkData
        The simulated data.

    Returns
    -------
    NetworkTrack
        ``method="centralised"``; the estimate is repeated for every node.

    Examples
    --------
    >>> from cifilter.network import centralised, ring, simulate_data
    >>> scenario = ring(4)
    >>> centralised(scenario, simulate_data(scenario, 2, 3, rng=0)).x.shape
    (2, 3, 4, 4)
    """
    n, nodes = scenario.dim, scenario.nodes
    runs, steps = data.runs, data.steps
    H = np.concatenate(scenario.H)
    sizes = [h.shape[0] for h in scenario.H]
    R = np.zeros((sum(sizes), sum(sizes)))
    at = 0
    for size, Ri in zip(sizes, scenario.R):
        R[at:at + size, at:at + size] = Ri
        at += size
    z = np.concatenate(data.measurements, axis=-1)
    # the priors are independent: their information-form product is exact
    information = np.linalg.inv(scenario.P0)
    P = np.linalg.inv(information.sum(axis=0))
    x = np.einsum("ij,rj->ri", P, np.einsum("mij,rmj->ri", information, data.initial))
    P = np.broadcast_to(P, (runs, n, n))
    out_x, out_P = np.empty((runs, steps, n)), np.empty((runs, steps, n, n))
    for k in range(steps):
        x, P = _predict(x, P, scenario.F, scenario.Q)
        x, P, _, _ = _update(x, P, z[:, k], H, R)
        out_x[:, k], out_P[:, k] = x, P
    shape = (runs, steps, nodes)
    return NetworkTrack("centralised", np.broadcast_to(out_x[:, :, None], shape + (n,)),
                        np.broadcast_to(out_P[:, :, None], shape + (n, n)))
