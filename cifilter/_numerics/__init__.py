"""What every rule shares (private): Cholesky-based linear algebra (:mod:`.linalg`), input
validation (:mod:`.validation`), the one weighted information fusion (:mod:`.information`),
the criteria and their certificates (:mod:`.criteria`) and the convex solvers
(:mod:`.optimize`). The floor beneath the rules and the kernels: it imports no other part of
cifilter.
"""
