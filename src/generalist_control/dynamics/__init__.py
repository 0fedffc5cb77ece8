"""Nonlinear plant dynamics ``f(x, u, **params)``, batched, named by ``conf/plants/*.yaml``."""
