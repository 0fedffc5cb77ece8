"""The notebooks: committed without outputs, and executed end to end on tiny data.

The notebooks read their settings from environment variables (``GC_DATA_DIR``,
``MLFLOW_TRACKING_URI``, ...), which these tests point at the tiny dataset and at synthetic
MLflow runs. Execution uses the notebook runner of the ``notebooks`` extra (nbclient with an
ipykernel kernel; ``dev`` includes it, so ``make setup`` installs it): without it these tests
skip and say so.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ablation_runs import PLANTS, log_runs

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
MISSING = "the notebook runner is not installed: pip install -e '.[dev]'"


def _execute(path: Path) -> None:
    nbformat = pytest.importorskip("nbformat", reason=MISSING)
    nbclient = pytest.importorskip("nbclient", reason=MISSING)
    pytest.importorskip("ipykernel", reason=MISSING)
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        nb,
        timeout=300,
        kernel_name="python3",
        resources={"metadata": {"path": str(path.parent)}},
    )
    client.execute()  # raises CellExecutionError, with the cell and traceback, on failure
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors


def test_there_are_notebooks():
    names = {p.name for p in NOTEBOOKS}
    assert {"01_plants_and_data.ipynb", "02_mlflow_comparison.ipynb"} <= names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_committed_without_outputs(path):
    """The nbstripout rule: no outputs, execution counts or widget state in git."""
    nb = json.loads(path.read_text())
    for i, cell in enumerate(nb["cells"]):
        if cell["cell_type"] == "code":
            assert cell.get("outputs") == [], f"{path.name}, cell {i}: strip its outputs"
            assert cell.get("execution_count") is None, f"{path.name}, cell {i}"
        assert "execution" not in cell.get("metadata", {}), f"{path.name}, cell {i}"
    assert "widgets" not in nb.get("metadata", {})


@pytest.mark.slow
def test_plants_and_data_notebook_runs(tiny_data_dir, monkeypatch):
    monkeypatch.setenv("GC_DATA_DIR", str(tiny_data_dir))
    monkeypatch.setenv("GC_PLANTS", "cstr,hydraulic_actuator")
    monkeypatch.setenv("GC_DURATION", "3")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    _execute(ROOT / "notebooks" / "01_plants_and_data.ipynb")


@pytest.mark.slow
def test_mlflow_comparison_notebook_runs(tmp_path, mlflow_uri, monkeypatch):
    log_runs(mlflow_uri, tmp_path.name, tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", mlflow_uri)
    monkeypatch.setenv("GC_EXPERIMENT", tmp_path.name)
    monkeypatch.setenv("GC_PLANTS", ",".join(PLANTS))
    monkeypatch.setenv("GC_GATE_DURATION", "2")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    _execute(ROOT / "notebooks" / "02_mlflow_comparison.ipynb")
