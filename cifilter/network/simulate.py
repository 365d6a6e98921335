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

import numbers
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Optional, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .._numerics.linalg import cholesky
from .._numerics.validation import as_float_array, as_rng, check_int, check_scalar
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
    lateness : ndarray of int, shape (runs, steps, nodes, nodes), or None
        ``lateness[r, k, i, j]``: node ``j``'s estimate of step ``k`` reaches node ``i``
        that many steps late, at step ``k + lateness[r, k, i, j]`` (None: every message
        arrives at the step it is sent). Messages of different steps therefore arrive out
        of order; :func:`run_network`'s ``late=`` says what a node does with them.

    Examples
    --------
    >>> from cifilter.network import ring, simulate_data
    >>> data = simulate_data(ring(4), runs=3, steps=5, rng=0)
    >>> data.truth.shape, data.initial.shape, data.delivered is None, data.lateness is None
    ((3, 5, 4), (3, 4, 4), True, True)
    """

    truth: NDArray[np.float64]
    measurements: tuple[NDArray[np.float64], ...]
    initial: NDArray[np.float64]
    delivered: Optional[NDArray[np.bool_]] = None
    lateness: Optional[NDArray[np.int_]] = None

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
                  lateness: Union[int, Sequence[float]] = 0,
                  rng: Optional[Union[int, np.random.Generator]] = None) -> NetworkData:
    """Simulate the target, the measurements, the initial estimates, the packet losses and
    the messages' lateness.

    Parameters
    ----------
    scenario : Scenario
        The network and its models.
    runs, steps : int
        Monte Carlo runs and time steps.
    loss : float, optional
        Probability that a message between linked nodes is lost, independently per
        message, direction and step (default 0).
    lateness : int or sequence of float, optional
        How many steps late each message arrives, drawn independently per message,
        direction and step: an integer ``L`` draws it uniformly from ``0, 1, ..., L``; a
        sequence ``(p_0, ..., p_L)`` gives the probability of each lateness (non-negative,
        summing to 1). Default 0: every message arrives at the step it is sent
        (``data.lateness`` is None and nothing is drawn, so the other draws are those of
        a call without ``lateness``).
    rng : numpy.random.Generator, int or None, optional
        Randomness (the only source; same seed, same data).

    Returns
    -------
    NetworkData
        The data, drawn in this order: initial errors, process noises, each node's
        measurement noises, losses, lateness.

    Raises
    ------
    ValueError
        If ``runs`` or ``steps`` is below 1, ``loss`` is outside [0, 1], ``lateness`` is
        a negative integer, or its probabilities are negative, not finite, empty or do not
        sum to 1.
    TypeError
        If ``lateness`` is neither an integer nor a sequence of numbers.

    Examples
    --------
    >>> from cifilter.network import naveen_taylor, simulate_data
    >>> data = simulate_data(naveen_taylor(), runs=2, steps=3, loss=0.2, rng=1)
    >>> data.delivered.shape, [z.shape for z in data.measurements][:2]
    ((2, 3, 6, 6), [(2, 3, 2), (2, 3, 2)])
    >>> late = simulate_data(naveen_taylor(), runs=2, steps=3, lateness=3, rng=1).lateness
    >>> late.shape, int(late.min()) >= 0 and int(late.max()) <= 3
    ((2, 3, 6, 6), True)
    """
    if not isinstance(scenario, Scenario):
        raise TypeError(f"scenario must be a Scenario, got {type(scenario).__name__}")
    runs, steps = check_int(runs, "runs", low=1), check_int(steps, "steps", low=1)
    loss = check_scalar(loss, "loss", low=0, high=1)
    chances = _lateness_chances(lateness)
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
    late = None
    if chances is not None:
        late = rng.choice(chances.size, size=(runs, steps, nodes, nodes), p=chances)
    return NetworkData(truth, tuple(measurements), initial, delivered, late)


def _lateness_chances(lateness):
    """The probabilities of lateness 0, 1, ..., L (None when every message is on time)."""
    if isinstance(lateness, (numbers.Integral, np.integer)) and not isinstance(
            lateness, (bool, np.bool_)):
        steps = check_int(int(lateness), "lateness", low=0)
        return None if steps == 0 else np.full(steps + 1, 1.0 / (steps + 1))
    if isinstance(lateness, (str, bytes, bool, np.bool_)) or not hasattr(lateness, "__len__"):
        raise TypeError("lateness must be an integer L (uniform over 0..L steps) or a sequence "
                        f"of probabilities of 0, 1, 2, ... steps, got {type(lateness).__name__}")
    chances = as_float_array(lateness, "lateness")
    if chances.ndim != 1 or chances.size == 0:
        raise ValueError("lateness must be a non-empty sequence of probabilities (of 0, 1, "
                         f"2, ... steps), got shape {chances.shape}")
    if not np.all(np.isfinite(chances)) or np.any(chances < 0):
        raise ValueError(f"lateness probabilities must be finite and >= 0, got {chances.tolist()}")
    if abs(chances.sum() - 1.0) > 1e-9:
        raise ValueError(f"lateness probabilities must sum to 1, got {chances.sum():.12g}")
    chances = chances / chances.sum()
    return None if chances.size == 1 else chances


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


LATE_POLICIES = ("align", "ignore", "drop")
"""What a node does with a track that arrives late (``run_network(late=...)``)."""

PARTIAL_POLICIES = ("fuse", "drop")
"""What a node does with a track of part of the state (``run_network(partial=...)``)."""


def _check_config(period, sequential, delay, feedback):
    period = check_int(period, "period", low=1)
    for name, value in (("sequential", sequential), ("delay", delay), ("feedback", feedback)):
        if not isinstance(value, (bool, np.bool_)):
            raise TypeError(f"{name} must be True or False, got {value!r}")
    return period


def _check_choice(value, name, allowed):
    if not isinstance(value, str):
        raise TypeError(f"{name} must be one of {', '.join(map(repr, allowed))}, got "
                        f"{type(value).__name__}")
    if value not in allowed:
        raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got "
                         f"{value!r}")
    return value


def _partial_senders(scenario, partial_nodes):
    """``{node: S}``: the nodes that send only ``S x`` and ``S P S^T`` of their track."""
    if partial_nodes is None:
        return {}
    n, nodes = scenario.dim, scenario.nodes
    if isinstance(partial_nodes, Mapping):
        items = list(partial_nodes.items())
    elif isinstance(partial_nodes, (str, bytes)) or not hasattr(partial_nodes, "__iter__"):
        raise TypeError("partial_nodes must be a sequence of node indices (they send the "
                        "position block) or a mapping {node: (m, n) matrix}, got "
                        f"{type(partial_nodes).__name__}")
    else:
        position = np.eye(n)[list(scenario.position_indices)]
        items = [(node, position) for node in partial_nodes]
    senders = {}
    for node, S in items:
        if isinstance(node, (bool, np.bool_)) or not isinstance(node, numbers.Integral):
            raise TypeError(f"partial_nodes must name nodes by their index, got {node!r}")
        if not 0 <= node < nodes:
            raise ValueError(f"partial_nodes names node {node}, outside 0..{nodes - 1}")
        if int(node) in senders:
            raise ValueError(f"partial_nodes names node {node} twice")
        S = as_float_array(S, f"partial_nodes[{node}]")
        if S.ndim != 2 or S.shape[0] == 0 or S.shape[1] != n:
            raise ValueError(f"partial_nodes[{node}] must be a matrix of shape (m, {n}), got "
                             f"shape {S.shape}")
        if not np.all(np.isfinite(S)) or np.linalg.matrix_rank(S) < S.shape[0]:
            raise ValueError(f"partial_nodes[{node}] must be finite with linearly independent "
                             "rows (the track S x it sends needs a positive definite S P S^T)")
        senders[int(node)] = S
    return senders


def _check_lateness(data, runs, steps, nodes):
    """``data.lateness`` checked against the data (None when every message is on time)."""
    if data.lateness is None:
        return None
    late = np.asarray(data.lateness)
    if late.shape != (runs, steps, nodes, nodes):
        raise ValueError(f"data.lateness must have shape {(runs, steps, nodes, nodes)}, got "
                         f"{late.shape}")
    if late.dtype.kind not in "iu":
        raise TypeError(f"data.lateness must hold integers (steps), got dtype {late.dtype}")
    if late.size and late.min() < 0:
        raise ValueError("data.lateness must be >= 0 (a message cannot arrive before it is "
                         "sent)")
    return late


def run_network(scenario: Scenario, data: NetworkData, method: Optional[str] = "ci", *,
                feedback: bool = True, period: int = 1, sequential: bool = False,
                delay: bool = False, late: str = "align",
                partial_nodes: Optional[Union[Sequence[int], Mapping[int, ArrayLike]]] = None,
                partial: str = "fuse", rng: Optional[Union[int, np.random.Generator]] = None,
                options: Optional[Mapping[str, Any]] = None) -> NetworkTrack:
    """Run the decentralised network with one fusion rule over all runs at once.

    Parameters
    ----------
    scenario : Scenario
        The network and its models.
    data : NetworkData
        Truth, measurements, initial estimates, delivered messages and their lateness
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
        indices (several tracks of one neighbour: the newest first), each into the result
        of the previous fusion (two estimates per call); default False fuses the node's
        own estimate and all received ones in one call.
    delay : bool, optional
        Messages arrive one step late: a node fuses its neighbours' estimates of the
        previous step, brought to the current time by the target model (their predicted
        estimates, before their own update). Default False. Not with ``data.lateness``.
    late : {"align", "ignore", "drop"}, optional
        What a node does with a track that arrives late (``data.lateness``, drawn by
        ``simulate_data(lateness=...)``): a message is the sender's updated estimate of
        the step it is sent (before that step's fusion) and is fused at the step it
        arrives, together with whatever else arrives then (out of order: an older track
        may arrive after a newer one, and several tracks of one sender may arrive at
        once). ``"align"`` (default) fuses a track of step ``k - d`` at step ``k`` through
        the front door's time alignment, ``cifilter.fuse(..., times=, at=k,
        motion=scenario.motion)``: it is predicted ``d`` steps with the target model,
        exactly (``docs/methods/time.rst``). ``"ignore"`` fuses it as if it were of step
        ``k``; ``"drop"`` fuses only the tracks that arrive on time. Without
        ``data.lateness`` the three are the same.
    partial_nodes : sequence of int or mapping, optional
        Nodes whose tracks hold only part of the state: a sequence of node indices (each
        sends only the position block of its track, the rows ``scenario.position_indices``
        of ``x`` and ``P``) or a mapping ``{node: S}`` (node sends ``S x`` and ``S P S^T``,
        ``S`` of shape (m, n) with independent rows). Their own filters keep the full
        state and fuse full tracks as every node does. Default: none.
    partial : {"fuse", "drop"}, optional
        What a node does with a partial track: fuse it through the front door's ``H=``
        (generalised CI for ``"ci"``; ``docs/methods/partial_state.rst``; ``"optimal"``
        is told the true joint covariance of the partial estimates; a rule that does not
        accept ``H=`` raises the front door's error) or drop it. Default ``"fuse"``.
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
        Unknown method or policy, data that does not fit the scenario, ``delay`` with
        ``data.lateness``, a node of ``partial_nodes`` out of range or repeated or a
        matrix of the wrong shape; a rule with a truth hook (``"optimal"``, ``"pci"``)
        with late tracks fused (``late="align"`` or ``"ignore"``: the simulation
        propagates the true joint covariance of tracks fused at the step they are sent
        only); ``late="align"`` with late tracks of part of the state (the front door
        predicts full-state estimates only); or what the rule raises (for instance a
        truth hook that cannot handle more than two estimates, or a rule that does not
        accept ``H=`` given partial tracks).
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

    Tracks that arrive up to three steps late, predicted to the time they are fused; two
    nodes that send only their position block, fused through ``H=``:

    >>> late = simulate_data(scenario, runs=3, steps=10, lateness=3, rng=0)
    >>> run_network(scenario, late, "ci", late="align").x.shape
    (3, 10, 6, 4)
    >>> run_network(scenario, data, "ci", partial_nodes=[1, 4]).fusions
    180
    """
    period = _check_config(period, sequential, delay, feedback)
    late = _check_choice(late, "late", LATE_POLICIES)
    partial = _check_choice(partial, "partial", PARTIAL_POLICIES)
    senders = _partial_senders(scenario, partial_nodes)
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
    lateness = _check_lateness(data, runs, steps, nodes)
    if lateness is not None and delay:
        raise ValueError("delay=True brings every message one step late, predicted; "
                         "data.lateness (simulate_data(lateness=...)) delays each message "
                         "by its own draw: give one or the other")
    need_joint = record is not None and record.truth_options is not None
    # how many steps back a fused track may be (0: every fused track is of this step)
    depth = 0 if lateness is None or late == "drop" else int(
        lateness[:, :, scenario.adjacency].max(initial=0))
    fused_partial = sorted(senders) if partial == "fuse" else []
    if record is not None:
        if need_joint and depth:
            raise ValueError(
                f"rule {record.name!r} is told the true joint covariance of the estimates it "
                "fuses (its truth hook); the simulation propagates it for tracks fused at the "
                "step they are sent only, not for late tracks: use late='drop'")
        if late == "align" and depth and fused_partial and (
                (lateness[:, :, :, fused_partial] > 0)
                & scenario.adjacency[:, fused_partial]).any():
            raise ValueError(
                f"partial_nodes {fused_partial} send tracks of part of the state that arrive "
                "late, and late='align' cannot bring them to the current time (the front "
                "door predicts estimates of the full state only); use late='ignore' or "
                "'drop', or partial='drop'")
    sources = _Sources(scenario, senders if fused_partial else {}, depth, late == "align",
                       sequential)
    keep = None  # the senders whose tracks are fused (None: all)
    if senders and partial == "drop":
        keep = np.ones(nodes, dtype=bool)
        keep[sorted(senders)] = False
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
    sent: list = []  # the sent estimates of the last depth + 1 steps, newest first
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
        sending = not (k + 1) % period
        if record is None or not (sending or depth):
            out_x[:, k], out_P[:, k] = x, P
            continue
        exchanges += sending
        sent = [(x_prior, P_prior) if delay else (x, P)] + sent[:depth]
        sent += sent[-1:] * (depth + 1 - len(sent))  # (steps before the first: never received)
        received = _arrivals(scenario.adjacency, data.delivered, lateness, k, period,
                             depth + 1, runs)
        if keep is not None:
            received = received & keep
        if not sending and not received.any():
            out_x[:, k], out_P[:, k] = x, P
            continue
        messages_x, messages_P, received = sources.sorted(sent, received)
        base = None
        if delay:
            if need_joint:  # base errors: [updated of every node, predicted of every node]
                cross = A_big @ joint_prior
                base = np.block([[joint, cross], [np.swapaxes(cross, -1, -2), joint_prior]])
            offset = nodes
        else:
            base, offset = joint, 0
        start = time.perf_counter()
        fused_x, fused_P, maps, count = _exchange(
            record, x, P, messages_x, messages_P, received, sources, k, offset, base,
            sequential, rng, options, n)
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


def _arrivals(adjacency, delivered, lateness, k, period, depth, runs):
    """``received[r, i, d, j]``: node ``j``'s track of step ``k - d`` reaches node ``i`` at
    step ``k`` (sent at an exchange step, delivered, ``d`` steps late), for ``d < depth``
    (read-only when every track is on time)."""
    nodes = adjacency.shape[0]
    if depth == 1 and lateness is None:  # sent and received at this exchange step
        received = np.broadcast_to(adjacency, (runs, nodes, nodes))
        if delivered is not None:
            received = received & delivered[:, k]
        return received[:, :, None]
    received = np.zeros((runs, nodes, depth, nodes), dtype=bool)
    for d in range(depth):
        s = k - d
        if s < 0 or (s + 1) % period:
            continue
        arrived = np.broadcast_to(adjacency, (runs, nodes, nodes))
        if delivered is not None:
            arrived = arrived & delivered[:, s]
        if lateness is not None:
            arrived = arrived & (lateness[:, s] == d)
        received[:, :, d] = arrived
    return received


class _Sources:
    """The tracks a node may receive at one step: sender ``j``'s track of ``d`` steps ago,
    full or partial, in a fixed order: (sender, lateness) for sequential fusion, else (kind,
    lateness, sender) so that every item of a batched fusion has the same kind of estimate
    in each slot.

    ``category`` of a source is ``g * depth1 + d`` with ``g`` 0 for a full track, else the
    index of its sender's matrix in ``matrices`` (``matrices[0]`` is None)."""

    def __init__(self, scenario, senders, depth, align, sequential):
        nodes = scenario.nodes
        self.depth1, self.align, self.motion = depth + 1, align, scenario.motion
        self.matrices = [None]
        kind = np.zeros(nodes, dtype=int)
        for node, S in senders.items():
            same = [g for g, M in enumerate(self.matrices[1:], start=1)
                    if M.shape == S.shape and np.array_equal(M, S)]
            if not same:
                self.matrices.append(S)
            kind[node] = same[0] if same else len(self.matrices) - 1
        lag = np.repeat(np.arange(self.depth1), nodes)
        sender = np.tile(np.arange(nodes), self.depth1)
        # one at a time: in the senders' order (newest track first); all at once: sorted
        # by kind so that the items of a batch hold the same kind in each slot
        self.order = np.lexsort((lag, sender)) if sequential else np.lexsort(
            (sender, lag, kind[sender]))
        self.category = (kind[sender] * self.depth1 + lag)[self.order]
        self.sender = sender[self.order]
        self.plain = depth == 0 and not senders  # every source is a full track of now

    def sorted(self, sent, received):
        """The sent means and covariances (runs, M, ...) and ``received`` (runs, nodes, M),
        in the sources' order (``sent``: one (x, P) per lateness, newest first)."""
        runs, nodes = received.shape[:2]
        received = received.reshape(runs, nodes, -1)
        if self.plain:
            return sent[0][0], sent[0][1], received
        messages_x = np.concatenate([x for x, _ in sent], axis=1)[:, self.order]
        messages_P = np.concatenate([P for _, P in sent], axis=1)[:, self.order]
        return messages_x, messages_P, received[..., self.order]

    def slots(self, categories, k):
        """The matrices of the slots (None: full) and the front-door options of a fusion
        of the node's own estimate with tracks of these categories at step ``k``."""
        lag, kind = categories % self.depth1, categories // self.depth1
        matrices = [self.matrices[g] for g in kind]
        front = {}
        if kind.any():
            front["H"] = [None, *matrices]
        if self.align and lag.any():
            front.update(times=[float(k), *(float(k - d) for d in lag)], at=float(k),
                         motion=self.motion)
        return matrices, front


def _exchange(record, x, P, messages_x, messages_P, received, sources, k, offset, base,
              sequential, rng, options, n):
    """Fuse every node's estimate with its received messages (one step, all runs).

    ``received`` (runs, nodes, M) says which of the M sources (``sources``' order, the
    order of ``messages_x``, ``messages_P``) reached each node. Returns the fused means
    and covariances, the maps ``M`` (runs, nodes, n, B n) of the fused errors as linear
    functions of the base errors (when ``base``, the joint covariance of the base errors,
    is given), and the number of fusions.
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
    category = sources.category
    if sequential:
        # slot s of node i: the s-th message it received, in the sources' order
        order = np.cumsum(received, axis=-1) - 1
        for s in range(received.shape[-1]):
            r_idx, i_idx, m_idx = np.nonzero(received & (order == s))
            if r_idx.size == 0:
                break
            if sources.plain:
                groups = [(r_idx, i_idx, m_idx[:, None])]
            else:  # one batch per kind of track in this slot
                kinds = category[m_idx]
                groups = [(r_idx[kinds == c], i_idx[kinds == c], m_idx[kinds == c][:, None])
                          for c in np.unique(kinds)]
            count += _fuse_groups(record, groups, fused_x, fused_P, messages_x, messages_P,
                                  maps, offset, base, rng, options, n, category, sources, k)
        return fused_x, fused_P, maps, count
    counts = received.sum(axis=-1)
    groups = []
    if sources.plain:  # one batch per number of received tracks
        for c in np.unique(counts[counts > 0]):
            r_idx, i_idx = np.nonzero(counts == c)
            j_idx = np.nonzero(received[r_idx, i_idx])[1].reshape(-1, c)
            groups.append((r_idx, i_idx, j_idx))
    else:  # one batch per number of received tracks of each kind (kind, lateness)
        kinds = np.unique(category)
        rows = received.astype(np.int64) @ (category[:, None] == kinds).astype(np.int64)
        active = counts > 0
        for key in np.unique(rows[active], axis=0):
            r_idx, i_idx = np.nonzero(active & (rows == key).all(axis=-1))
            j_idx = np.nonzero(received[r_idx, i_idx])[1].reshape(-1, int(key.sum()))
            groups.append((r_idx, i_idx, j_idx))
    count += _fuse_groups(record, groups, fused_x, fused_P, messages_x, messages_P, maps,
                          offset, base, rng, options, n, category, sources, k)
    return fused_x, fused_P, maps, count


def _fuse_groups(record, groups, fused_x, fused_P, messages_x, messages_P, maps, offset,
                 base, rng, options, n, category, sources, k):
    """Fuse each group (runs r, nodes i, received j (B, c)) in one call; in place."""
    count = 0
    for r_idx, i_idx, j_idx in groups:
        c = j_idx.shape[1]
        xs = np.concatenate([fused_x[r_idx, i_idx][:, None], messages_x[r_idx[:, None], j_idx]],
                            axis=1)
        Ps = np.concatenate([fused_P[r_idx, i_idx][:, None],
                             messages_P[r_idx[:, None], j_idx]], axis=1)
        estimates = [(xs[:, s], Ps[:, s]) for s in range(c + 1)]
        front = {}
        matrices = [None] * c
        senders = j_idx
        if not sources.plain:
            matrices, front = sources.slots(category[j_idx[0]], k)
            senders = sources.sender[j_idx]
            for s, S in enumerate(matrices, start=1):
                if S is not None:
                    P_S = S @ Ps[:, s] @ S.T
                    estimates[s] = (xs[:, s] @ S.T, 0.5 * (P_S + np.swapaxes(P_S, -1, -2)))
        partial = any(S is not None for S in matrices)
        call_options = dict(options)
        rows = None
        if base is not None:
            size = base.shape[-1]
            rows = np.zeros((r_idx.size, c + 1, n, size))
            rows[:, 0] = maps[r_idx, i_idx]
            columns = (offset + senders)[..., None] * n + np.arange(n)  # (B, c, n)
            batch = np.arange(r_idx.size)[:, None, None]
            slot = np.arange(1, c + 1)[None, :, None]
            rows[batch, slot, np.arange(n)[None, None, :], columns] = 1.0
            if partial:  # the rows of each estimate: S e_j for a partial track
                rows = [rows[:, 0]] + [rows[:, s] if S is None else S @ rows[:, s]
                                       for s, S in enumerate(matrices, start=1)]
                flat = np.concatenate(rows, axis=1)
            else:
                flat = rows.reshape(r_idx.size, (c + 1) * n, size)
            joint = flat @ base[r_idx] @ np.swapaxes(flat, -1, -2)
            joint = 0.5 * (joint + np.swapaxes(joint, -1, -2))
            sizes = ([n] + [n if S is None else S.shape[0] for S in matrices]
                     if partial else None)
            call_options.update(record.options_given_truth(joint, rng, count=c + 1,
                                                           sizes=sizes))
        result = fuse(estimates, method=record.name, **front, **call_options)
        fused_x[r_idx, i_idx] = np.asarray(result.x).reshape(r_idx.size, n)
        fused_P[r_idx, i_idx] = result.P
        if rows is not None:
            gains = result.info.get("gains") if partial else result.gains
            if gains is None:
                raise ValueError(
                    f"rule {record.name!r} returns no gains: the joint covariance its truth "
                    "hook needs cannot be propagated")
            if partial:  # K_s of shape (n, m_s): the fused error is sum_s K_s rows_s
                maps[r_idx, i_idx] = sum(np.broadcast_to(K, (r_idx.size,) + K.shape[-2:])
                                         @ row for K, row in zip(gains, rows))
            else:
                gains = np.broadcast_to(gains, (r_idx.size, c + 1, n, n))
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
