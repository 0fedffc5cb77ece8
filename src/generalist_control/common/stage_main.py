"""``hydra.main`` for the stages, composing the config once instead of twice.

Hydra 1.3 composes the whole config a first time only to read ``hydra.mode``
(``Hydra.get_mode``), then again to run: about half of a stage's start-up composition.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import hydra
from hydra._internal.hydra import Hydra
from omegaconf import DictConfig

from generalist_control.common.paths import conf_dir

__all__ = ["stage_main"]

#: The override keys that set Hydra's mode on the command line.
_MODE_KEYS = ("hydra.mode=", "+hydra.mode=", "++hydra.mode=")


@contextmanager
def _mode_from_the_command_line() -> Iterator[None]:
    """``Hydra.get_mode`` answers from the overrides, without composing the config.

    No config of the project sets ``hydra.mode``: ``-m`` / ``--multirun`` or an override
    ``hydra.mode=MULTIRUN`` does (docs/sweeps.md). Where an override names the mode, Hydra's
    own ``get_mode`` reads it as before.
    """
    original = Hydra.get_mode

    def get_mode(self: Hydra, config_name: str | None, overrides: list[str]) -> Any:
        if any(o.startswith(_MODE_KEYS) for o in overrides):
            return original(self, config_name, overrides)
        return None  # what Hydra's get_mode returns for a config that leaves the mode unset

    Hydra.get_mode = get_mode  # type: ignore[method-assign]
    try:
        yield
    finally:
        Hydra.get_mode = original  # type: ignore[method-assign]


def stage_main(config_name: str) -> Callable[[Callable[[DictConfig], Any]], Callable[..., Any]]:
    """``@hydra.main`` on the project's configs (``conf/``, or ``GC_CONF_DIR``).

    Parameters
    ----------
    config_name : str
        The primary config of the stage (``config``, ``tune``, ``adapt``, ...).
    """

    def decorate(task: Callable[[DictConfig], Any]) -> Callable[..., Any]:
        @functools.wraps(task)
        def main(cfg_passthrough: DictConfig | None = None) -> Any:
            # the folder as the command starts (GC_CONF_DIR then), not as it was imported
            path = str(conf_dir())
            hydra_main = hydra.main(version_base="1.3", config_path=path, config_name=config_name)
            with _mode_from_the_command_line():
                return hydra_main(task)(cfg_passthrough)

        return main

    return decorate
