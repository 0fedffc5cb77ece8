"""Training: the data module, the Lightning module, DAgger, callbacks and the fit itself."""
