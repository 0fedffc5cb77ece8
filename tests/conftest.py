"""Shared fixtures: a tiny demonstration dataset of two plants of different order."""

from __future__ import annotations

import compileall
import json
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

from generalist_control.data.demos import DemoSet, write_demos
from generalist_control.data.generation import build_manifest, generate_demos
from generalist_control.plants.catalog import load_plant
from generalist_control.tracking import mlflow_utils
from helpers import TINY_DATA

# A shell that starts the suite in the background ignores SIGINT, and the commands the tests
# start would inherit that: the tests that send them Ctrl-C need Python's default handler.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# One thread: the tiny batches gain nothing from two, and on a shared 2-core machine a second
# OpenMP thread that waits for a busy core can stall every step by orders of magnitude.
torch.set_num_threads(1)

#: Each test file's measured seconds (scripts/test_durations.py), to hand out the longest first.
DURATIONS = Path(__file__).with_name("durations.json")

#: Two plants of order 2 and 3, eight step amplitudes each, 2 s (40 samples) per trajectory.
TINY_PLANTS = ("cstr", "hydraulic_actuator")


@pytest.fixture(autouse=True)
def no_parent_run(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every test starts outside a sweep: no parent run in the environment (and any a test
    leaves behind is removed afterwards), whatever ran before it in the same worker."""
    for key in (mlflow_utils.PARENT_RUN_ENV, mlflow_utils.SWEEP_ENV):
        monkeypatch.delenv(key, raising=False)


@pytest.fixture(scope="session")
def tiny_demos() -> DemoSet:
    plants = [load_plant(name) for name in TINY_PLANTS]
    return generate_demos(plants, TINY_DATA, progress=False)


@pytest.fixture(scope="session")
def tiny_data_dir(tmp_path_factory: pytest.TempPathFactory, tiny_demos: DemoSet) -> Path:
    """``data/demos`` of the tiny set, written by the data stage's own writer."""
    plants = [load_plant(name) for name in TINY_PLANTS]
    config = {"systems": {"name": "tiny", "include": list(TINY_PLANTS)}, "data": TINY_DATA}
    manifest = build_manifest(plants, tiny_demos, TINY_DATA, config)
    return write_demos(tmp_path_factory.mktemp("data") / "demos", tiny_demos, manifest)


@pytest.fixture(scope="session")
def mlflow_uri(tmp_path_factory: pytest.TempPathFactory) -> str:
    """One SQLite MLflow store for the session (creating its tables takes a few seconds)."""
    return f"sqlite:///{tmp_path_factory.mktemp('mlflow') / 'mlflow.db'}"


@pytest.fixture(scope="session")
def postgres_url() -> Iterator[str]:
    """A throw-away PostgreSQL server (tests/pg.py): the URL of its database ``optuna``.

    Fails, rather than skips, when PostgreSQL is not installed: ``bash scripts/postgres.sh``.
    """
    from pg import PostgresUnavailable, postgres_server

    server = postgres_server()
    try:
        url = server.__enter__()
    except PostgresUnavailable as e:
        pytest.fail(str(e), pytrace=False)
    try:
        yield url
    finally:
        server.__exit__(None, None, None)


def pytest_sessionstart(session: pytest.Session) -> None:
    """The package byte-compiled once, before any test: each process the suite starts (DVC
    stages, launcher workers, fork servers) reads it instead of compiling it again, about
    1 CPU s each where ``PYTHONDONTWRITEBYTECODE`` keeps Python from writing what it compiles."""
    if not hasattr(session.config, "workerinput"):  # the controller, not each xdist worker
        compileall.compile_dir(Path(__file__).parents[1] / "src", quiet=1)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Files longest first (tests/durations.json, measured: scripts/test_durations.py), then
    those with the most slow tests, then the rest in their order: the workers (``--dist
    loadfile --no-loadscope-reorder``) then end on short files, not one on a long one."""
    seconds = json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {}
    slow: dict[str, int] = {}
    for item in items:
        slow[_file(item)] = slow.get(_file(item), 0) + (
            item.get_closest_marker("slow") is not None
        )
    order = {f: i for i, f in enumerate(dict.fromkeys(_file(i) for i in items))}
    items.sort(key=lambda i: (-seconds.get(_file(i), 0.0), -slow[_file(i)], order[_file(i)]))


def _file(item: pytest.Item) -> str:
    return item.nodeid.split("::")[0]


@pytest.fixture(autouse=True)
def _mlflow_active_experiment_restored() -> Iterator[None]:
    """A test that sets MLflow's active experiment (process-wide) does not set it for the
    tests after it in the same worker."""
    import os

    from mlflow.tracking import fluent

    saved, env = fluent._active_experiment_id, os.environ.get("MLFLOW_EXPERIMENT_ID")
    yield
    fluent._active_experiment_id = saved
    if env is None:
        os.environ.pop("MLFLOW_EXPERIMENT_ID", None)
    else:
        os.environ["MLFLOW_EXPERIMENT_ID"] = env
