"""The Hydra callback's former path, kept so configs that name it keep working.

``conf/hydra_settings.yaml`` names
:class:`generalist_control.sweeps.hydra_callback.MLflowSweepCallback`.
"""

from generalist_control.sweeps.hydra_callback import MLflowSweepCallback, sweep_overrides

__all__ = ["MLflowSweepCallback", "sweep_overrides"]
