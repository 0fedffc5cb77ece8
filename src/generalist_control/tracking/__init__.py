"""Experiment tracking: MLflow runs, their parameters, and parent runs of sweeps and studies."""
