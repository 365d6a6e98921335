"""Sensor networks: the graph, the nodes' sensor models and ready scenarios.

A :class:`Scenario` is everything a simulation of decentralised tracking needs: the
target's linear model (``F``, ``Q``, its initial state), each node's sensor (``H_i``,
``R_i``) and prior covariance, and who talks to whom (a symmetric adjacency matrix).
Ready scenarios: :func:`naveen_taylor` (the six-node network of Naveen & Taylor,
Section V-B), :func:`ring`, :func:`chain` (the k nodes of Weng & Djurić's distributed
Kalman filter model) and :func:`fully_connected`; :func:`two_tracks` is the two sensors of
the two-track demo; :func:`common_information` is two such nodes tracking a target with no
process noise, where the correlation between the nodes is common information (Noack et
al.'s model, the one Inverse CI assumes). :meth:`Scenario.from_filters` builds a scenario
from the user's own ``cifilter.KalmanFilter`` objects and graph; :meth:`Scenario.motion` is
its model over several steps, the ``motion=`` of :func:`cifilter.fuse` for late tracks.
"""

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from .._numerics.validation import as_float_array, check_covariances, check_int, check_scalar

__all__ = [
    "NAVEEN_TAYLOR_EDGES",
    "Scenario",
    "adjacency_matrix",
    "chain",
    "common_information",
    "constant_velocity_model",
    "fully_connected",
    "get_scenario",
    "naveen_taylor",
    "ring",
    "scenario_names",
    "two_tracks",
]

NAVEEN_TAYLOR_EDGES = ((0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (1, 4))
"""Edges of Naveen & Taylor's six-node network (their Fig. 5 is missing from the text;
a ring with one chord, as in :mod:`cifilter.cli.reproduce.naveen`)."""

POSITION = (0, 2)  # x and y in the state [x, vx, y, vy]
_START = np.array([0.0, 10.0, 0.0, 5.0])
_PRIOR = np.diag([100.0, 25.0, 100.0, 25.0])


def constant_velocity_model(
        dt: float, q: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """State transition and process noise of a 2-D constant-velocity model.

    Parameters
    ----------
    dt : float
        Time step [s].
    q : float
        Power spectral density of the white-noise acceleration [m^2/s^3].

    Returns
    -------
    F, Q : ndarray, shape (4, 4)
        For the state ``[x, vx, y, vy]``.

    Examples
    --------
    >>> from cifilter.network import constant_velocity_model
    >>> F, Q = constant_velocity_model(1.0, 0.1)
    >>> F[0].tolist()
    [1.0, 1.0, 0.0, 0.0]
    """
    F1 = np.array([[1.0, dt], [0.0, 1.0]])
    Q1 = q * np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
    # numpy's stubs type np.kron of float64 arrays as floating[Any]
    return np.kron(np.eye(2), F1), np.kron(np.eye(2), Q1)  # type: ignore[return-value]


def _position_sensor():
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 2] = 1.0
    return H


def adjacency_matrix(graph: Any, nodes: Optional[int] = None) -> NDArray[np.bool_]:
    """A symmetric boolean adjacency matrix from a matrix, an edge list or a graph object.

    Parameters
    ----------
    graph : ndarray or sequence of pairs or graph
        An ``(m, m)`` numpy array, the adjacency matrix (non-zero entries are links; it
        must be symmetric: links are two-way), a sequence of ``(i, j)`` edges between
        nodes ``0..m-1``, or a ``networkx`` graph (any object with ``nodes`` and
        ``edges``; networkx itself is not needed). Self-loops are ignored.
    nodes : int, optional
        Number of nodes for an edge list (default: one more than the largest index).

    Returns
    -------
    ndarray of bool, shape (m, m)
        ``A[i, j]`` is True when nodes ``i`` and ``j`` exchange estimates; the diagonal is
        False. For a graph object the nodes are numbered in ``list(graph.nodes)`` order.

    Raises
    ------
    ValueError
        If a matrix is not square or not symmetric, or an edge names a node out of range.

    Examples
    --------
    >>> from cifilter.network import adjacency_matrix
    >>> adjacency_matrix([(0, 1), (1, 2)]).astype(int).tolist()
    [[0, 1, 0], [1, 0, 1], [0, 1, 0]]
    """
    if hasattr(graph, "nodes") and hasattr(graph, "edges"):
        order = {node: i for i, node in enumerate(list(graph.nodes))}
        edges = [(order[a], order[b]) for a, b, *_ in graph.edges]
        return adjacency_matrix(edges, nodes=len(order))
    if isinstance(graph, np.ndarray) and graph.ndim == 2 and graph.shape[0] == graph.shape[1]:
        matrix = np.asarray(graph) != 0
        if not np.array_equal(matrix, matrix.T):
            raise ValueError("the adjacency matrix must be symmetric (links are two-way)")
    else:
        edges = [tuple(edge) for edge in graph]
        if any(len(edge) != 2 for edge in edges):
            raise ValueError("an edge list must hold (i, j) pairs of node indices")
        count = (1 + max((max(edge) for edge in edges), default=-1)) if nodes is None \
            else check_int(nodes, "nodes", low=1)
        matrix = np.zeros((count, count), dtype=bool)
        for i, j in edges:
            if not (0 <= i < count and 0 <= j < count):
                raise ValueError(f"edge {(i, j)} names a node outside 0..{count - 1}")
            matrix[i, j] = matrix[j, i] = True
    np.fill_diagonal(matrix, False)
    return matrix


@dataclass(frozen=True)
class Scenario:
    """A sensor network tracking one target with a linear model.

    The parameters are also the attributes. The target moves as ``x_k = F x_{k-1} + w_k``,
    ``w_k ~ N(0, Q)``, from ``x0``; node ``i`` measures ``z_i = H_i x + v_i``,
    ``v_i ~ N(0, R_i)``, runs a Kalman filter with the model ``F``, ``Q``, ``H_i``, ``R_i``
    from an independent prior ``N(x0 + e_i, P0_i)`` (``e_i ~ N(0, P0_i)``) and exchanges
    estimates with its neighbours in ``adjacency``.

    Parameters
    ----------
    name : str
        Short name.
    F, Q : ndarray, shape (n, n)
        Target model (transition and process noise covariance).
    H : tuple of ndarray, shapes (m_i, n)
        Measurement matrix of each node.
    R : tuple of ndarray, shapes (m_i, m_i)
        Measurement noise covariance of each node.
    adjacency : ndarray of bool, shape (nodes, nodes)
        Symmetric, with a False diagonal (see :func:`adjacency_matrix`).
    x0 : ndarray, shape (n,)
        Initial true state.
    P0 : ndarray, shape (nodes, n, n)
        Prior covariance of each node's filter (its initial error is drawn from it).
    positions : ndarray, shape (nodes, 2)
        Where to draw the nodes (layout only).
    description : str
        One paragraph on where the scenario comes from.
    position_indices : tuple of int
        State components that are the target's position (RMSE and ellipses).

    Examples
    --------
    >>> from cifilter.network import naveen_taylor
    >>> s = naveen_taylor()
    >>> s.nodes, s.dim, s.degrees.tolist()
    (6, 4, [2, 3, 2, 2, 3, 2])
    """

    name: str
    F: NDArray[np.float64]
    Q: NDArray[np.float64]
    H: tuple[NDArray[np.float64], ...]
    R: tuple[NDArray[np.float64], ...]
    adjacency: NDArray[np.bool_]
    x0: NDArray[np.float64]
    P0: NDArray[np.float64]
    positions: Optional[NDArray[np.float64]] = None
    description: str = ""
    position_indices: tuple[int, ...] = POSITION

    def __post_init__(self):
        F = as_float_array(self.F, "F")
        n = F.shape[-1]
        if F.shape != (n, n):
            raise ValueError(f"F must be a square matrix, got shape {F.shape}")
        Q = as_float_array(self.Q, "Q")
        if Q.shape != (n, n):
            raise ValueError(f"Q must have shape {(n, n)}, got {Q.shape}")
        adjacency = adjacency_matrix(self.adjacency)
        nodes = adjacency.shape[0]
        H = tuple(as_float_array(h, f"H[{i}]") for i, h in enumerate(self.H))
        R = tuple(as_float_array(r, f"R[{i}]") for i, r in enumerate(self.R))
        if len(H) != nodes or len(R) != nodes:
            raise ValueError(f"H and R need one matrix per node ({nodes}), got {len(H)} "
                             f"and {len(R)}")
        for i, (h, r) in enumerate(zip(H, R)):
            if h.ndim != 2 or h.shape[1] != n:
                raise ValueError(f"H[{i}] must have shape (m, {n}), got {h.shape}")
            if r.shape != (h.shape[0], h.shape[0]):
                raise ValueError(f"R[{i}] must have shape {(h.shape[0],) * 2}, got {r.shape}")
            check_covariances(r, f"R[{i}]")
        P0 = as_float_array(self.P0, "P0")
        P0 = np.broadcast_to(P0, (nodes, n, n)).copy() if P0.shape in ((n, n), (nodes, n, n)) \
            else None
        if P0 is None:
            raise ValueError(f"P0 must have shape ({n}, {n}) or ({nodes}, {n}, {n})")
        check_covariances(P0, "P0")
        x0 = as_float_array(self.x0, "x0").reshape(-1)
        if x0.shape != (n,):
            raise ValueError(f"x0 must have {n} entries, got {x0.size}")
        positions = self.positions
        if positions is None:
            angle = 2 * np.pi * np.arange(nodes) / nodes
            positions = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
        positions = as_float_array(positions, "positions")
        if positions.shape != (nodes, 2):
            raise ValueError(f"positions must have shape ({nodes}, 2), got {positions.shape}")
        for name, value in (("F", F), ("Q", Q), ("H", H), ("R", R), ("adjacency", adjacency),
                            ("x0", x0), ("P0", P0), ("positions", positions),
                            ("position_indices", tuple(int(i) for i in self.position_indices))):
            object.__setattr__(self, name, value)
        if not np.allclose(Q, Q.T) or np.linalg.eigvalsh(Q)[0] < -1e-12 * np.abs(Q).max():
            raise ValueError("Q must be symmetric positive semidefinite")

    @property
    def nodes(self) -> int:
        """Number of nodes.

        Returns
        -------
        int
            The number of nodes.

        Examples
        --------
        >>> from cifilter.network import ring
        >>> ring(5).nodes
        5
        """
        return self.adjacency.shape[0]

    @property
    def dim(self) -> int:
        """Dimension of the state.

        Returns
        -------
        int
            ``n``.

        Examples
        --------
        >>> from cifilter.network import ring
        >>> ring(5).dim
        4
        """
        return self.F.shape[0]

    @property
    def degrees(self) -> NDArray[np.int_]:
        """Number of neighbours of each node.

        Returns
        -------
        ndarray of int, shape (nodes,)
            Row sums of the adjacency matrix.

        Examples
        --------
        >>> from cifilter.network import chain
        >>> chain(4).degrees.tolist()
        [1, 2, 2, 1]
        """
        return self.adjacency.sum(axis=1)

    @property
    def edges(self) -> list[tuple[int, int]]:
        """The links as ``(i, j)`` pairs with ``i < j``.

        Returns
        -------
        list of tuple
            One pair per link.

        Examples
        --------
        >>> from cifilter.network import chain
        >>> chain(3).edges
        [(0, 1), (1, 2)]
        """
        i, j = np.nonzero(np.triu(self.adjacency))
        return [(int(a), int(b)) for a, b in zip(i, j)]

    def motion(self, dt: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The target model over ``dt`` steps: the ``motion=`` of :func:`cifilter.fuse`
        for times counted in steps.

        ``x_{k+dt} = F_dt x_k + w`` with ``F_dt = F^dt`` and ``w`` the process noise of
        the ``dt`` steps, of covariance ``Q_dt = sum_{s<dt} F^s Q F^sT`` (the recursion
        ``Q_{s+1} = F Q_s F^T + Q``): the simulation's own model, so a track predicted
        with it is predicted exactly. For :func:`constant_velocity_model` this is the
        model of the longer time step, ``constant_velocity_model(dt * step, q)``, to
        rounding.

        Parameters
        ----------
        dt : float
            Number of steps, a whole number >= 0 (``cifilter.fuse`` passes
            ``|at - times[i]|`` as a float).

        Returns
        -------
        F, Q : ndarray, shape (n, n)
            Transition and process noise covariance over ``dt`` steps (new arrays; the
            identity and zero for ``dt = 0``).

        Raises
        ------
        ValueError
            If ``dt`` is negative, not finite or not a whole number of steps.
        TypeError
            If ``dt`` is not a real number.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter.network import constant_velocity_model, ring
        >>> F3, Q3 = ring(4).motion(3)
        >>> F, Q = constant_velocity_model(3.0, 0.5)    # ring's model has dt 1, q 0.5
        >>> bool(np.allclose(F3, F) and np.allclose(Q3, Q))
        True
        """
        steps = check_scalar(dt, "dt", low=0)
        if steps != round(steps):
            raise ValueError(f"dt must be a whole number of steps, got {dt!r}")
        F = np.eye(self.dim)
        Q = np.zeros((self.dim, self.dim))
        for _ in range(round(steps)):
            F = self.F @ F
            Q = self.F @ Q @ self.F.T + self.Q
        return F, 0.5 * (Q + Q.T)

    def with_graph(self, graph: Any) -> "Scenario":
        """The same nodes with other links.

        Parameters
        ----------
        graph : array_like or sequence of pairs or graph
            See :func:`adjacency_matrix`; it must have the same number of nodes.

        Returns
        -------
        Scenario
            A copy with the new adjacency.

        Raises
        ------
        ValueError
            If the number of nodes differs.

        Examples
        --------
        >>> from cifilter.network import ring
        >>> ring(4).with_graph([(0, 2)]).degrees.tolist()
        [1, 0, 1, 0]
        """
        adjacency = adjacency_matrix(graph, nodes=self.nodes)
        if adjacency.shape[0] != self.nodes:
            raise ValueError(f"the graph has {adjacency.shape[0]} nodes, the scenario "
                             f"{self.nodes}")
        return Scenario(self.name, self.F, self.Q, self.H, self.R, adjacency, self.x0,
                        self.P0, self.positions, self.description, self.position_indices)

    @classmethod
    def from_filters(cls, filters: Iterable[Any], graph: Any, *, x0: Optional[ArrayLike] = None,
                     name: str = "custom",
                     positions: Optional[ArrayLike] = None) -> "Scenario":
        """A scenario from the user's own filters (one per node) and graph.

        Each filter gives its node's sensor (``H``, ``R``) and prior covariance ``P``;
        the target model ``F``, ``Q`` must be the same in every filter (it is also the
        truth's model in the simulation).

        Parameters
        ----------
        filters : sequence of filter
            ``cifilter.KalmanFilter`` (or filterpy) objects with ``F``, ``Q``, ``H``,
            ``R``, ``x``, ``P``; they are read, not modified.
        graph : array_like or sequence of pairs or graph
            Who exchanges with whom (see :func:`adjacency_matrix`).
        x0 : array_like, optional
            Initial true state (default: the first filter's ``x``).
        name : str, optional
            Name of the scenario.
        positions : array_like, shape (nodes, 2), optional
            Layout for drawing.

        Returns
        -------
        Scenario
            The scenario.

        Raises
        ------
        ValueError
            If the filters disagree on ``F`` or ``Q`` or the graph's size differs.

        Examples
        --------
        >>> import numpy as np
        >>> from cifilter import KalmanFilter
        >>> from cifilter.network import Scenario
        >>> filters = []
        >>> for r in (1.0, 4.0):
        ...     kf = KalmanFilter(dim_x=2, dim_z=1)
        ...     kf.F = np.array([[1.0, 1.0], [0.0, 1.0]])
        ...     kf.Q, kf.H, kf.R = 0.1 * np.eye(2), np.array([[1.0, 0.0]]), np.array([[r]])
        ...     filters.append(kf)
        >>> s = Scenario.from_filters(filters, [(0, 1)])
        >>> s.nodes, s.position_indices
        (2, (0,))
        """
        filters = list(filters)
        if not filters:
            raise ValueError("filters must hold one filter per node")
        F, Q = np.asarray(filters[0].F, float), np.asarray(filters[0].Q, float)
        for i, kf in enumerate(filters[1:], start=1):
            if not (np.array_equal(np.asarray(kf.F, float), F)
                    and np.array_equal(np.asarray(kf.Q, float), Q)):
                raise ValueError(f"filters[{i}] has another F or Q than filters[0]: the "
                                 "nodes must share the target model")
        adjacency = adjacency_matrix(graph, nodes=len(filters))
        if adjacency.shape[0] != len(filters):
            raise ValueError(f"the graph has {adjacency.shape[0]} nodes, there are "
                             f"{len(filters)} filters")
        x0 = np.asarray(filters[0].x, float).reshape(-1) if x0 is None else x0
        n = F.shape[0]
        # x0 and positions may be array-likes: __post_init__ converts them (and checks them)
        return cls(name, F, Q, tuple(np.atleast_2d(np.asarray(kf.H, float)) for kf in filters),
                   tuple(np.atleast_2d(np.asarray(kf.R, float)) for kf in filters), adjacency,
                   x0,  # type: ignore[arg-type]
                   np.stack([np.asarray(kf.P, float) for kf in filters]),
                   positions,  # type: ignore[arg-type]
                   "user-defined filters and graph",
                   POSITION if n == 4 else (0,))


def _circle(nodes):
    angle = np.pi / 2 - 2 * np.pi * np.arange(nodes) / nodes
    return np.stack([np.cos(angle), np.sin(angle)], axis=-1)


def _alternating_sensors(nodes):
    """The two-track demo's sensors A (sigma 10, 2 m) and B (3, 8 m), alternately."""
    R_a, R_b = np.diag([100.0, 4.0]), np.diag([9.0, 64.0])
    return tuple(R_a if i % 2 == 0 else R_b for i in range(nodes))


def _build(name, adjacency, R, positions, description, dt, q):
    F, Q = constant_velocity_model(dt, q)
    nodes = len(R)
    return Scenario(name, F, Q, (_position_sensor(),) * nodes, tuple(R), adjacency, _START,
                    _PRIOR, positions, description)


def naveen_taylor(*, sigma: float = 5.0, dof: int = 30, dt: float = 1.0, q: float = 0.5,
                  sensor_seed: int = 2) -> Scenario:
    """The six-node network of Naveen & Taylor (Section V-B), tracking a moving target.

    The topology is that of their Fig. 5 as :mod:`cifilter.cli.reproduce.naveen` reads it (the
    figure is missing from the text: a ring of six with the chord 1-4,
    :data:`NAVEEN_TAYLOR_EDGES`). As their nodes start with covariances drawn from an
    inverse Wishart distribution with 30 degrees of freedom, each node here measures the
    target's position with a noise covariance drawn once from ``W^-1(dof sigma^2 I, dof)``
    (mean about ``sigma^2 I``; fixed by ``sensor_seed``, not by the Monte Carlo seed). The
    paper fuses static estimates; here the target moves as in the two-track demo (2-D
    constant velocity), and every node also filters its own measurements.

    Parameters
    ----------
    sigma : float, optional
        Typical standard deviation of a position measurement [m] (default 5).
    dof : int, optional
        Degrees of freedom of the inverse Wishart distribution (default 30, the paper's).
    dt, q : float, optional
        Time step [s] and white-noise acceleration density [m^2/s^3] (defaults 1, 0.5).
    sensor_seed : int, optional
        Seed of the draw of the sensors' covariances.

    Returns
    -------
    Scenario
        Six nodes, seven links.

    Examples
    --------
    >>> from cifilter.network import naveen_taylor
    >>> naveen_taylor().edges
    [(0, 1), (0, 5), (1, 2), (1, 4), (2, 3), (3, 4), (4, 5)]
    """
    sigma = check_scalar(sigma, "sigma", low=0, low_open=True)
    dof = check_int(dof, "dof", low=4)
    draws = stats.invwishart.rvs(df=dof, scale=dof * sigma**2 * np.eye(2), size=6,
                                 random_state=np.random.default_rng(sensor_seed))
    description = ("Naveen & Taylor, Section V-B: six nodes (Fig. 5: a ring with the chord "
                   f"1-4), position sensors with covariances from W^-1({dof} sigma^2 I, {dof}),"
                   f" sigma = {sigma:g} m")
    return _build("naveen-taylor", adjacency_matrix(NAVEEN_TAYLOR_EDGES), list(draws),
                  _circle(6), description, dt, q)


def ring(nodes: int = 6, *, dt: float = 1.0, q: float = 0.5) -> Scenario:
    """A ring of nodes with the two-track demo's sensors A and B alternating.

    Parameters
    ----------
    nodes : int, optional
        Number of nodes (at least 3; default 6).
    dt, q : float, optional
        Time step [s] and white-noise acceleration density [m^2/s^3].

    Returns
    -------
    Scenario
        Every node linked to the next, the last to the first.

    Examples
    --------
    >>> from cifilter.network import ring
    >>> ring(4).edges
    [(0, 1), (0, 3), (1, 2), (2, 3)]
    """
    nodes = check_int(nodes, "nodes", low=3)
    edges = [(i, (i + 1) % nodes) for i in range(nodes)]
    return _build("ring", adjacency_matrix(edges), _alternating_sensors(nodes),
                  _circle(nodes), f"a ring of {nodes} nodes, sensors A (sigma 10, 2 m) and B "
                  "(3, 8 m) alternating", dt, q)


def fully_connected(nodes: int = 4, *, dt: float = 1.0, q: float = 0.5) -> Scenario:
    """Every node linked to every other, sensors A and B alternating.

    Parameters
    ----------
    nodes : int, optional
        Number of nodes (at least 2; default 4).
    dt, q : float, optional
        Time step [s] and white-noise acceleration density [m^2/s^3].

    Returns
    -------
    Scenario
        The complete graph.

    Examples
    --------
    >>> from cifilter.network import fully_connected
    >>> fully_connected(3).degrees.tolist()
    [2, 2, 2]
    """
    nodes = check_int(nodes, "nodes", low=2)
    adjacency = ~np.eye(nodes, dtype=bool)
    return _build("fully-connected", adjacency, _alternating_sensors(nodes), _circle(nodes),
                  f"{nodes} nodes, all linked, sensors A and B alternating", dt, q)


def chain(nodes: int = 5, *, sigma: float = 5.0, dt: float = 1.0, q: float = 0.5,
          sensor_seed: int = 3) -> Scenario:
    """A chain of k nodes with the sensors of Weng & Djurić's distributed Kalman filter
    model (journal, model 2, eqs. (54)-(56)).

    Their k estimates of a common state have independent noises with covariances
    ``Sigma_i ~ W_2(3, sigma^2 I)``; here node ``i`` measures the moving target's position
    with such a covariance (drawn once, fixed by ``sensor_seed``), and node ``i`` exchanges
    with nodes ``i - 1`` and ``i + 1`` only (five nodes by default, their Fig. 10).

    Parameters
    ----------
    nodes : int, optional
        Number of nodes k (at least 2; default 5).
    sigma : float, optional
        Scale of the sensor covariances [m] (default 5: ``sigma^2 I`` in m^2).
    dt, q : float, optional
        Time step [s] and white-noise acceleration density [m^2/s^3].
    sensor_seed : int, optional
        Seed of the draw of the sensors' covariances.

    Returns
    -------
    Scenario
        A path graph.

    Examples
    --------
    >>> from cifilter.network import chain
    >>> chain(3).degrees.tolist()
    [1, 2, 1]
    """
    nodes = check_int(nodes, "nodes", low=2)
    sigma = check_scalar(sigma, "sigma", low=0, low_open=True)
    draws = stats.wishart.rvs(df=3, scale=sigma**2 * np.eye(2), size=nodes,
                              random_state=np.random.default_rng(sensor_seed))
    draws = np.asarray(draws).reshape(nodes, 2, 2)
    positions = np.stack([np.linspace(-1, 1, nodes), np.zeros(nodes)], axis=-1)
    return _build("chain", adjacency_matrix([(i, i + 1) for i in range(nodes - 1)]),
                  list(draws), positions,
                  f"Weng & Djuric's k = {nodes} nodes as a chain, position sensors with "
                  f"covariances from W_2(3, sigma^2 I), sigma = {sigma:g} m", dt, q)


def two_tracks(*, dt: float = 1.0, q: float = 0.5, sigma_a: tuple[float, float] = (10.0, 2.0),
               sigma_b: tuple[float, float] = (3.0, 8.0)) -> Scenario:
    """The two sensors of the two-track demo (``python -m cifilter demo --scenario
    two-tracks``) as a network of two linked nodes.

    Parameters
    ----------
    dt, q : float, optional
        Time step [s] and white-noise acceleration density [m^2/s^3].
    sigma_a, sigma_b : tuple of float, optional
        Standard deviations [m] of sensors A and B in x and y.

    Returns
    -------
    Scenario
        Two nodes, one link.

    Examples
    --------
    >>> from cifilter.network import two_tracks
    >>> two_tracks().R[0].diagonal().tolist()
    [100.0, 4.0]
    """
    R = (np.diag(np.square(sigma_a)), np.diag(np.square(sigma_b)))
    return _build("two-tracks", adjacency_matrix([(0, 1)]), R,
                  np.array([[-1.0, 0.0], [1.0, 0.0]]),
                  "the two-track demo's sensors A and B, linked", dt, q)


def common_information(*, dt: float = 1.0, q: float = 0.0,
                       sigma_a: tuple[float, float] = (10.0, 2.0),
                       sigma_b: tuple[float, float] = (3.0, 8.0)) -> Scenario:
    """Two linked nodes whose correlation is common information: a target with no process
    noise, tracked with feedback.

    The two-track demo's sensors A and B, linked, tracking a target that moves at constant
    velocity without process noise (``q = 0``). With feedback (the demo's default) both
    nodes fuse each other's estimate with the same symmetric rule and so hold the same
    fused estimate; each then predicts (exactly, ``Q = 0``) and updates with its own,
    independent measurement. Their errors are therefore ``e_a = P_a (n_a + c)``,
    ``e_b = P_b (n_b + c)``: an exclusive part ``n_a``, ``n_b`` (the new measurement's
    information) and a common part ``c`` (the shared fused estimate's), so
    ``P_ab = P_a C P_b`` with ``C = F^-T P_f^-1 S_f P_f^-1 F^-1`` (``P_f``, ``S_f``: the
    fused estimate's reported and true covariances). For a conservative rule
    (``S_f <= P_f``) this ``C`` is symmetric with ``0 <= C <= P_a^-1, P_b^-1``: the
    common-information model of Noack et al. (2017) under which Inverse CI (``"ici"``)
    is a bound, and the true joint covariance is dominated by the model's joint with the
    reported ``P_a``, ``P_b``. Before the first exchange the priors are independent
    (``C = 0``).

    Two nodes, because each node then fuses exactly two estimates (ICI's bound is proved
    for two). What makes the correlation common information is that the nodes start every
    step from the same estimate and add only independent information to it; with feedback
    that holds for any ``q`` (the process noise hits the shared estimate). Without
    feedback each filter stays local: with ``q = 0`` the local estimates are independent
    (``C = 0``); with ``q > 0`` the process noise they share makes ``P_a^-1 P_ab P_b^-1``
    non-symmetric, a correlation outside the model (measured here: while the filters
    converge; it approaches the model at their steady state). In the other scenarios,
    where every node holds a different combination of estimates, the common process noise
    is not common information.

    Parameters
    ----------
    dt : float, optional
        Time step [s] (default 1).
    q : float, optional
        White-noise acceleration density [m^2/s^3] (default 0: common information only).
    sigma_a, sigma_b : tuple of float, optional
        Standard deviations [m] of sensors A and B in x and y.

    Returns
    -------
    Scenario
        Two nodes, one link, ``Q = q``-scaled (zero by default).

    References
    ----------
    B. Noack, J. Sijs, M. Reinhardt, U. D. Hanebeck, "Decentralized data fusion with
    inverse covariance intersection", Automatica 79, 2017 (the common-information model).

    Examples
    --------
    >>> from cifilter.network.graph import common_information
    >>> s = common_information()
    >>> s.nodes, float(abs(s.Q).max())
    (2, 0.0)
    """
    q = check_scalar(q, "q", low=0)
    R = (np.diag(np.square(sigma_a)), np.diag(np.square(sigma_b)))
    description = ("common information: the two-track demo's sensors A and B, linked, "
                   "tracking a target without process noise"
                   + ("" if q == 0 else f" (here with process noise q = {q:g})"))
    return _build("common-information", adjacency_matrix([(0, 1)]), R,
                  np.array([[-1.0, 0.0], [1.0, 0.0]]), description, dt, q)


_SCENARIOS: dict[str, Callable[..., Scenario]] = {
    "naveen-taylor": naveen_taylor,
    "ring": ring,
    "chain": chain,
    "fully-connected": fully_connected,
    "two-tracks": two_tracks,
    "common-information": common_information,
}


def scenario_names() -> tuple[str, ...]:
    """Names accepted by :func:`get_scenario`.

    Returns
    -------
    tuple of str
        The ready scenarios.

    Examples
    --------
    >>> from cifilter.network import scenario_names
    >>> scenario_names()[0]
    'naveen-taylor'
    """
    return tuple(_SCENARIOS)


def get_scenario(name: str, **options: Any) -> Scenario:
    """A ready scenario by name.

    Parameters
    ----------
    name : str
        One of :func:`scenario_names`.
    **options
        Passed to the scenario's function (e.g. ``nodes=8`` for a ring).

    Returns
    -------
    Scenario
        The scenario.

    Raises
    ------
    ValueError
        If the name is unknown (the message lists the known ones).

    Examples
    --------
    >>> from cifilter.network import get_scenario
    >>> get_scenario("ring", nodes=8).nodes
    8
    """
    try:
        build = _SCENARIOS[name]
    except (KeyError, TypeError):
        raise ValueError(f"unknown scenario {name!r}; known: {', '.join(_SCENARIOS)}") from None
    return build(**options)
