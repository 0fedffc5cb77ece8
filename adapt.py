"""Add a plant to a trained policy: ``python adapt.py plant=<name or path> [overrides]``.

A thin shim over :func:`generalist_control.adapt.main` (also the console script ``gc-adapt``
and ``python -m generalist_control.adapt``); see docs/training.md, "Adding a plant to a
trained policy".
"""

from generalist_control.adapt import main

if __name__ == "__main__":
    main()
