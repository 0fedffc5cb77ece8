"""Evaluation: the closed loop of a trained policy against LQI, its summary, tables and plots."""
