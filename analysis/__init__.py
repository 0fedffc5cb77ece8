"""Research investigations of the learned generalist (the tag-free diagnostics).

Kept apart from the product: :mod:`generalist_control` never imports this package
(``tests/test_layout.py`` checks it). Run from the repository root, e.g.
``python -m analysis.run_tag_free experiment=tag_free`` (the ``tag_free`` stage of
``beyond/dvc.yaml`` does). Its tests are ``tests/test_analysis_*.py``.
"""
