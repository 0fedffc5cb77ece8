"""Reports: the ablation study from MLflow runs, and the notebooks' plant and data tables."""
