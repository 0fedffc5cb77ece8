"""Generalist Controller: one neural policy that imitates LQI experts on many SISO plants."""

__version__ = "0.1.0"
