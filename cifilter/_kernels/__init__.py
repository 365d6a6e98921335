"""The compiled kernels of the Covariance Intersection family (private): the numba kernels
(:mod:`.compiled`, imported only when the numba backend runs them) and their dispatch
(:mod:`.dispatch`), which the rules call and which returns None where the backend
(:mod:`cifilter.backend`) keeps the numpy path. Beneath the rules; above :mod:`.._numerics`.
"""
