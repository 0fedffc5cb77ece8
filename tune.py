"""Search the Generalist Controller's hyper-parameters with Optuna: ``python tune.py``.

A thin shim over :func:`generalist_control.tune.main` (also the console script ``gc-tune``
and ``python -m generalist_control.tune``), e.g. ``python tune.py hparams_search=default
hparams_search.n_trials=50`` or, with several workers on one study,
``python tune.py hparams_search.storage=postgresql+psycopg2://user:pw@host/optuna``.
See docs/sweeps.md.
"""

from generalist_control.tune import main

if __name__ == "__main__":
    main()
