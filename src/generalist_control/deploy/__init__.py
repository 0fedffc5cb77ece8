"""Deployment: the real-time policy runtime, its export backends and simulator adapters."""
