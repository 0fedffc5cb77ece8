"""Sweeps and studies: Hydra multiruns grouped in MLflow, and the Optuna search."""
