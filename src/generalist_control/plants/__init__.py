"""Plant definitions, their configuration and the catalogue under ``conf/plants``.

The nonlinear plants' ``f(x, u)`` live in :mod:`generalist_control.dynamics` (the paths in
``conf/plants/*.yaml`` name them, and feed the dataset's content hash).
"""
