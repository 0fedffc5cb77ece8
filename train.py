"""Train the Generalist Controller: ``python train.py [hydra overrides]``.

A thin shim over :func:`generalist_control.train.main` (also the console script
``gc-train`` and ``python -m generalist_control.train``), e.g.
``python train.py model.hidden=64 experts=5`` or ``python train.py experiment=paper``.
"""

from generalist_control.train import main

if __name__ == "__main__":
    main()
