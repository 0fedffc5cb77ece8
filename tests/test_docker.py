"""docker/: the compose file's services and commands point at things that exist.

No Docker engine is needed: the YAML is parsed and checked here; where a Compose client is
installed (``docker compose`` or ``docker-compose``) it validates the file as well.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir

from generalist_control.common.paths import conf_dir

ROOT = Path(__file__).resolve().parents[1]
DOCKER = ROOT / "docker"


@pytest.fixture(scope="module")
def services() -> dict:
    spec = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    return spec["services"]


def _command(service: dict) -> str:
    cmd = service["command"]
    return " ".join(cmd) if isinstance(cmd, list) else cmd


def _hydra_overrides(command: str, script: str) -> list[str]:
    """The ``key=value`` arguments after ``python <script>`` in a shell command line."""
    words = shlex.split(command.replace("$$", "$"))
    start = words.index(script) + 1
    return [w for w in words[start:] if "=" in w and "$(" not in w]


def test_services_and_volumes(services):
    assert {"postgres", "mlflow", "pipeline", "tune-worker"} <= set(services)
    spec = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    assert {"pgdata", "mlartifacts"} <= set(spec["volumes"])
    # scalable with --scale: no fixed container name, no published host port
    worker = services["tune-worker"]
    assert "container_name" not in worker and "ports" not in worker


def test_mlflow_server_uses_postgres_and_an_artifact_volume(services):
    cmd = _command(services["mlflow"])
    assert cmd.split()[:2] == ["mlflow", "server"]
    assert re.search(r"--backend-store-uri postgresql\+psycopg2://\S+@postgres:5432/mlflow", cmd)
    assert "--artifacts-destination /mlartifacts" in cmd
    assert "--host 0.0.0.0" in cmd
    assert any(v.startswith("mlartifacts:/mlartifacts") for v in services["mlflow"]["volumes"])
    # every option exists in the installed MLflow
    help_text = subprocess.run(
        ["mlflow", "server", "--help"], capture_output=True, text=True, check=True
    ).stdout
    for option in re.findall(r"(--[a-z-]+)", cmd):
        assert option in help_text, option


def test_pipeline_runs_the_dvc_pipeline(services):
    assert _command(services["pipeline"]) == "dvc repro"
    assert (ROOT / "dvc.yaml").is_file()
    env = services["pipeline"]["environment"]
    assert env["MLFLOW_TRACKING_URI"] == "http://mlflow:5000"


def test_tune_worker_command_composes(services):
    cmd = _command(services["tune-worker"])
    assert "python tune.py" in cmd and (ROOT / "tune.py").is_file()
    overrides = _hydra_overrides(cmd, "tune.py")
    assert "hparams_search=default" in overrides
    assert "logger.tracking_uri=http://mlflow:5000" in overrides
    storage = next(o for o in overrides if o.startswith("hparams_search.storage="))
    assert storage.split("=", 1)[1].startswith("postgresql+psycopg2://")
    assert storage.endswith("@postgres:5432/optuna")
    assert services["tune-worker"]["environment"]["PGPASSWORD"].startswith("${POSTGRES_PASSWORD:?")
    # the worker number comes from the shell; any int composes
    assert re.search(r"hparams_search\.worker=\$\(", cmd.replace("$$", "$"))
    # compose variables (${POSTGRES_USER:-gc}) as Compose substitutes their defaults
    resolved = [re.sub(r"\$\{\w+:-(\w+)\}", r"\1", o) for o in overrides]
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose("config", overrides=[*resolved, "hparams_search.worker=3"])
    assert cfg.hparams_search.storage == "postgresql+psycopg2://gc@postgres:5432/optuna"
    assert cfg.logger.tracking_uri == "http://mlflow:5000"
    assert "CREATE DATABASE optuna" in (DOCKER / "postgres-init/01-databases.sql").read_text()


def test_no_default_password_and_mlflow_published_on_this_host_only(services):
    text = (DOCKER / "compose.yaml").read_text()
    # the password must be given (${VAR:?...}), and reaches the clients as PGPASSWORD only
    assert "POSTGRES_PASSWORD:-" not in text
    assert services["postgres"]["environment"]["POSTGRES_PASSWORD"].startswith(
        "${POSTGRES_PASSWORD:?"
    )
    for name in ("mlflow", "tune-worker"):
        assert "POSTGRES_PASSWORD" not in _command(services[name]), name
        assert services[name]["environment"]["PGPASSWORD"].startswith("${POSTGRES_PASSWORD:?")
    assert "PGPASSWORD" not in services["pipeline"]["environment"]  # it talks to MLflow only
    # the unauthenticated server: 127.0.0.1 unless MLFLOW_BIND says otherwise
    assert services["mlflow"]["ports"] == ["${MLFLOW_BIND:-127.0.0.1}:${MLFLOW_PORT:-5000}:5000"]


def test_dockerfile():
    text = (DOCKER / "Dockerfile").read_text()
    froms = [line for line in text.splitlines() if line.startswith("FROM ")]
    assert froms == ["FROM python:3.11-slim"]
    assert re.search(
        r"pip install torch==2\.13\.0 --index-url https://download\.pytorch\.org/whl/cpu", text
    )
    assert 'CMD ["dvc", "repro"]' in text
    for line in text.splitlines():
        if line.startswith("COPY "):
            for src in line.split()[1:-1]:
                assert (ROOT / src).exists(), f"COPY source {src} is missing"
    ignored = (DOCKER / "Dockerfile.dockerignore").read_text().split()
    assert {".git", ".venv", "data/demos", "mlruns"} <= set(ignored)


def _compose_client() -> list[str]:
    if (
        shutil.which("docker")
        and not subprocess.run(["docker", "compose", "version"], capture_output=True).returncode
    ):
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    pytest.fail(
        "no Compose client (docker compose / docker-compose): bash scripts/compose.sh "
        "installs Debian's docker-compose (make setup runs it)",
        pytrace=False,
    )


def _compose_config(**env: str) -> subprocess.CompletedProcess:
    """``<compose> config`` of the file, with ``env`` as the only Compose variables."""
    keep = {k: v for k, v in os.environ.items() if not k.startswith(("POSTGRES_", "MLFLOW_"))}
    return subprocess.run(
        [*_compose_client(), "-f", str(DOCKER / "compose.yaml"), "config"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**keep, **env},
    )


def test_compose_client_validates_the_file():
    proc = _compose_config(POSTGRES_PASSWORD="s3cret-pw")
    assert proc.returncode == 0, proc.stderr
    resolved = yaml.safe_load(proc.stdout)["services"]
    ports = str(resolved["mlflow"]["ports"])  # "127.0.0.1:5000:5000/tcp" or a long form
    assert "127.0.0.1" in ports and "0.0.0.0" not in ports
    assert resolved["mlflow"]["environment"]["PGPASSWORD"] == "s3cret-pw"
    assert "s3cret-pw" not in str(resolved["mlflow"]["command"])
    # without a password the file does not resolve; MLFLOW_BIND exposes the server on purpose
    missing = _compose_config()
    assert missing.returncode != 0 and "set POSTGRES_PASSWORD" in missing.stderr
    exposed = _compose_config(POSTGRES_PASSWORD="x", MLFLOW_BIND="0.0.0.0")
    assert exposed.returncode == 0, exposed.stderr
    assert "0.0.0.0" in str(yaml.safe_load(exposed.stdout)["services"]["mlflow"]["ports"])
