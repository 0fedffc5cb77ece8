"""``python tune.py [overrides]``: the Optuna study (generalist_control.tune, docs/sweeps.md)."""

from generalist_control.tune import main

if __name__ == "__main__":
    main()
