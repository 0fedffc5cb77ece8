"""Shared test utilities: compose the real Hydra config with overrides."""

from __future__ import annotations

from hydra import compose, initialize_config_dir

from generalist_control.paths import conf_dir


def compose_cfg(*overrides: str):
    """The project's primary config with ``overrides`` applied."""
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))
