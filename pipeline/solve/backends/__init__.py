"""The factorisation backends, one module each; importing this package registers them
with :mod:`pipeline.solve.factorization` in the order ``auto`` tries them (fastest
first, measured at 100k DOFs): PARDISO, SuperLU, CHOLMOD, and cuDSS (GPU, by name only).
"""

from pipeline.solve.backends import pardiso, superlu, cholmod, cudss  # noqa: F401
