"""Solvers: sparse factorisations (PARDISO, CHOLMOD, SuperLU) and the shift-invert
eigensolver that returns M-orthonormal modes."""
