"""Reduced models from the FE matrices and modes: the modal state space and its filtered
twin, the lumped chain, the connection-point (6x6) model, Craig-Bampton and the
floating-frame invariants."""
