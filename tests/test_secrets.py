"""No credential on stdout, stderr, the run folder or MLflow (issue 36, item 4).

One redaction (:func:`generalist_control.common.secrets.redact`) everywhere a config or URL
is printed or saved: URL passwords and credential query parameters; Hydra's own error line,
saved configs and log through :class:`~generalist_control.common.hydra_redact.RedactSecrets`
(registered in ``conf/hydra_settings.yaml``, composed by every entry point); MLflow run
names. The entry points run for real against ``127.0.0.1:9``, where nothing listens.
"""

from __future__ import annotations

import ast
import io
import json
import logging
import os
import sys
from pathlib import Path

import mlflow
import pytest
from hydra import compose, initialize_config_dir
from hydra.core.utils import JobReturn, JobStatus
from omegaconf import OmegaConf

from generalist_control.common.hydra_redact import RedactSecrets, redact_log_records
from generalist_control.common.paths import conf_dir
from generalist_control.common.secrets import RedactedError, redact, redact_exception
from generalist_control.tracking import mlflow_utils, parents, training_run
from helpers import run_command, sweep_callback

REPO = Path(__file__).resolve().parents[1]
SECRET = "Zq7-s3cr3t-PW"  # found nowhere else in the project's output

QUERIES = {
    "access_token": "https://h/api?access_token={s}&x=1",
    "api_key": "https://h/api?api_key={s}",
    "apikey": "https://h/api?x=1&apikey={s}",
    "sig": "https://acct.blob/c?sv=2024-01-01&sig={s}&se=2030",
    "signature": "https://h/o?Signature={s}",
    "X-Amz-Signature": "https://s3/o?X-Amz-Credential={s}&X-Amz-Signature={s}",
    "key": "https://maps/api?key={s}",
    "auth": "https://h/?auth={s}",
    "password": "http://h/?password={s}#frag",
    "fragment": "https://app/callback#access_token={s}&token_type=bearer",
    "sas": "https://acct.blob/c?sas={s}",
    "jwt": "https://h/?jwt={s}",
    "code": "https://h/cb?state=1&code={s}",
    "pat": "https://h/?pat={s}",
    "bearer": "https://h/?bearer={s}",
    "userinfo": "postgresql+psycopg2://gc:{s}@db:5432/optuna",
    "userinfo with /": "http://user:pa/{s}@host:5000/",
    "userinfo with @": "http://u:p@{s}@host/x",
    "userinfo with both": "http://u:/p@ss/{s}@host",
    "no scheme": "u:p@{s}@host",
    # Hydra's rendering of an override in a multirun (``#0 : ...``, .hydra/overrides.yaml)
    "hydra escaped": "logger.tracking_uri=http\\://user\\:pa/{s}@127.0.0.1\\:9/?token\\={s}",
    "json escaped": '["a=http\\\\://u\\\\:{s}@h"]',
    "two URLs": "a=http://u:{s}@h1/,http://v:{s}@h2/",
}


@pytest.mark.parametrize("name", list(QUERIES))
def test_every_kind_of_credential_in_a_url_is_masked(name):
    text = QUERIES[name].format(s=SECRET)
    masked = redact(text)
    assert SECRET not in masked and "p@" not in masked and "pa/" not in masked
    assert masked.count("***") == text.count(SECRET)


def test_a_password_is_masked_to_its_last_at_and_the_rest_kept():
    assert redact("u:p@ss@host") == "u:***@host"
    assert redact("see http://user:pa/SECRET@host/db?x=1.") == "see http://user:***@host/db?x=1."
    assert redact("a=http://u:p@h1/,http://v:q@h2/") == "a=http://u:***@h1/,http://v:***@h2/"
    assert redact("https://h/cb#access_token=t&token_type=bearer") == (
        "https://h/cb#access_token=***&token_type=bearer"
    )


def test_plain_parameters_and_urls_without_a_password_are_kept():
    text = "http://h:5000/api?experiment_name=gc%2Ftrain&run_id=abc&keyword=x&sv=1"
    assert redact(text) == text
    for kept in (
        "postgresql+psycopg2://gc@db:5432/optuna",  # a user name alone (PGPASSWORD elsewhere)
        "sqlite:////tmp/mlflow.db",
        "http://127.0.0.1:5000/#/experiments/1/runs/abc",
        "git@github.com:org/repo.git",
        "[2026-12-06 03:24:39,133][HYDRA] \t#0 : model.hidden=8 experts=3",
    ):
        assert redact(kept) == kept


def test_log_records_are_masked_whichever_handler_emits_them():
    """Records are masked when made: a handler set up later (Hydra reconfigures logging
    before a launcher logs ``#0 : ...``) gets them masked, message and traceback."""
    redact_log_records()
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)  # made after the masking was installed
    logger = logging.getLogger("test_secrets.late")
    logger.addHandler(handler)
    logger.propagate = False
    try:
        logger.warning("#0 : logger.tracking_uri=%s", f"http://u:pa/{SECRET}@h/?token={SECRET}")
        try:
            raise ConnectionError(f"no answer from http://u:{SECRET}@h/")
        except ConnectionError:
            logger.exception("store at %s", f"u:p@{SECRET}@h")
    finally:
        logger.removeHandler(handler)
    text = stream.getvalue()
    assert SECRET not in text
    assert "#0 : logger.tracking_uri=http://u:***@h/?token=***" in text
    assert "ConnectionError: no answer from http://u:***@h/" in text
    assert "store at u:***@h" in text


def test_params_logged_to_mlflow_are_masked():
    url = f"http://user:pa/{SECRET}@host/?token={SECRET}"
    params = mlflow_utils.flatten_params({"logger": {"tracking_uri": url}, "uris": [url]})
    assert SECRET not in json.dumps(params)
    assert params["logger.tracking_uri"] == "http://user:***@host/?token=***"


def test_an_error_and_the_errors_it_chains_are_masked():
    try:
        try:
            raise OSError(f"refused: http://u:{SECRET}@127.0.0.1:9/")
        except OSError as e:
            raise ValueError("store failed") from e
    except ValueError as e:
        err = redact_exception(e)
    assert isinstance(err, RedactedError) and err.__traceback__ is not None
    assert (
        str(err)
        == "ValueError: store failed\n  caused by OSError: refused: http://u:***@127.0.0.1:9/"
    )
    clean = KeyError("nothing secret")
    assert redact_exception(clean) is clean  # an error without credentials is kept as is


def test_hydra_prints_the_failed_jobs_overrides_and_error_masked(capsys):
    """Hydra's own ``Error executing job with overrides`` line, through the callback."""
    ret = JobReturn(overrides=[f"logger.tracking_uri=http://u:{SECRET}@h/"])
    ret.status = JobStatus.FAILED
    ret.return_value = ConnectionError(f"no answer from http://u:{SECRET}@h/")
    RedactSecrets().on_job_end(config=None, job_return=ret)
    with pytest.raises(RedactedError, match=r"http://u:\*\*\*@h/"):
        ret.return_value  # noqa: B018 (what Hydra does: print the line, raise the error)
    printed = capsys.readouterr().err
    assert "Error executing job with overrides: ['logger.tracking_uri=http://u:***@h/']" in printed
    assert SECRET not in printed


@pytest.mark.parametrize("config_name", ["config", "tune"])
def test_every_entry_point_config_registers_the_callback(config_name):
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose(config_name, return_hydra_config=True)
    targets = [str(c.get("_target_")) for c in cfg.hydra.callbacks.values()]
    assert "generalist_control.common.hydra_redact.RedactSecrets" in targets
    mains = {"generate", "train", "evaluate", "report", "tune"}
    for name in mains:  # each main composes one of these two
        tree = ast.parse((REPO / "src/generalist_control" / f"{name}.py").read_text())
        calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
        names = [  # @stage_main("<config>"), the stages' hydra.main
            c.args[0].value for c in calls if getattr(c.func, "id", None) == "stage_main"
        ]
        assert names and set(names) <= {"config", "tune"}, name


def _other_run(logger: dict) -> str:
    with mlflow_utils.mlflow_run(logger) as run:
        return run.info.run_id


OPENERS = {
    "training": lambda logger: training_run.training_logger(logger).run_id,
    "parent": lambda logger: parents.create_parent_run(logger, logger["run_name"], "sweep"),
    "other": _other_run,  # an evaluation's or a report's run
}


@pytest.mark.parametrize("kind", list(OPENERS))
def test_a_credential_in_a_run_name_is_masked(tmp_path, mlflow_uri, kind):
    logger = {
        "tracking_uri": mlflow_uri,
        "experiment_name": f"{tmp_path.name}",
        "artifact_location": str(tmp_path / "mlruns"),
        "run_name": f"d32?token={SECRET}",
    }
    run_id = OPENERS[kind](logger)
    run = mlflow.MlflowClient(mlflow_uri).get_run(run_id)
    assert run.info.run_name == "d32?token=***"
    assert all(SECRET not in v for v in run.data.tags.values())


def test_a_sweeps_parent_run_holds_no_password(tmp_path, mlflow_uri):
    """The parent's name and tags carry the overrides as Hydra renders them (escaped)."""
    cfg = OmegaConf.create(
        {
            "hydra": {
                "job": {"name": "train"},
                "overrides": {
                    "task": [
                        "model.hidden=8,16",
                        f"logger.tracking_uri=http\\://u\\:pa/{SECRET}@h/?token\\={SECRET}",
                        f"+note='http://u:p@{SECRET}@h/','u:p@{SECRET}@h'",  # swept too
                    ]
                },
                "sweep": {"dir": str(tmp_path)},
            },
            "logger": {
                "tracking_uri": mlflow_uri,
                "experiment_name": tmp_path.name,
                "artifact_location": str(tmp_path / "mlruns"),
            },
            "optimized_metric": "val/loss",
        }
    )
    callback = sweep_callback()
    callback.on_multirun_start(cfg)
    run = mlflow.MlflowClient(mlflow_uri).get_run(callback.run_id)
    callback.on_multirun_end(cfg)
    assert "***" in run.info.run_name and SECRET not in run.info.run_name
    assert "***" in run.data.tags["sweep.overrides"]
    assert all(SECRET not in v for v in run.data.tags.values())


# --- the entry points, run for real -------------------------------------------------------


def _run(cmd: list[str], run_dir: Path, *where: str) -> str:
    """Run ``cmd`` (it fails); no secret in its output or any file under ``run_dir``."""
    env = {**os.environ, "MLFLOW_HTTP_REQUEST_MAX_RETRIES": "0", "OMP_NUM_THREADS": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    proc = run_command(
        [*cmd, *(where or [f"hydra.run.dir={run_dir}"])],
        cwd=REPO,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 1, proc.stderr[-3000:]
    out = proc.stdout + proc.stderr
    assert "Error executing job with overrides" in out and "***" in out
    assert SECRET not in out
    saved = [p for p in run_dir.rglob("*") if p.is_file() and SECRET in p.read_text()]
    assert saved == [] and list(run_dir.rglob(".hydra/overrides.yaml"))
    return out


def test_train_against_an_unreachable_tracking_server(tmp_path, tiny_data_dir):
    """The issue's case: the error line and MLflow's URL held the password."""
    uri = f"http://user:pa/{SECRET}@127.0.0.1:9/"  # a "/" in the password
    cmd = [sys.executable, "train.py", f"logger.tracking_uri={uri}"]
    cmd += [f"paths.data_dir={tiny_data_dir}", "trainer.accelerator=cpu"]
    cmd += ["systems.include=[cstr,hydraulic_actuator]"]
    out = _run(cmd, tmp_path / "run")
    assert "the MLflow tracking store http://user:***@127.0.0.1:9/ (logger.tracking_uri)" in out


def test_tune_with_an_unreachable_storage(tmp_path):
    """The issue's case: the project's error was masked, Hydra's line and files were not."""
    url = f"postgresql://user:{SECRET}@127.0.0.1:9/optuna"
    out = _run([sys.executable, "tune.py", f"hparams_search.storage={url}"], tmp_path / "run")
    assert "postgresql://user:***@127.0.0.1:9/optuna" in out


def test_evaluate_refuses_an_unreachable_tracking_server_masked(tmp_path):
    """Asked before the policy (here a runs:/ URI MLflow would fetch) or anything else."""
    uri = f"http://user:{SECRET}@127.0.0.1:9/"
    cmd = [sys.executable, "-m", "generalist_control.evaluate", f"logger.tracking_uri={uri}"]
    cmd += ["policy=runs:/0123456789abcdef/policy", f"paths.reports_dir={tmp_path / 'eval'}"]
    out = _run(cmd, tmp_path / "run")
    assert "the MLflow tracking store http://user:***@127.0.0.1:9/ (logger.tracking_uri)" in out
    assert not (tmp_path / "eval").exists()


@pytest.mark.parametrize("launcher", ["basic", pytest.param("joblib", marks=pytest.mark.slow)])
def test_a_multirun_prints_and_saves_no_password(tmp_path, tiny_data_dir, launcher):
    """Hydra's own ``#0 : <overrides>`` lines, the jobs' and the sweep's saved configs."""
    uri = f"http://user:pa/{SECRET}@127.0.0.1:9/?token\\={SECRET}"
    cmd = [sys.executable, "train.py", "-m", "model.hidden=8,16", f"logger.tracking_uri={uri}"]
    cmd += [f"paths.data_dir={tiny_data_dir}", f"hydra/launcher={launcher}"]
    cmd += ["hydra.callbacks.mlflow_sweep.jobs=[]"]  # no parent run: the jobs reach the store
    sweep = tmp_path / "multirun"
    out = _run(cmd, sweep, f"hydra.sweep.dir={sweep}")
    line = r"#0 : model.hidden=8 logger.tracking_uri=http\://user\:***@127.0.0.1\:9/?token\=***"
    assert line in out
    assert (sweep / "multirun.yaml").is_file() and (sweep / "0/.hydra/config.yaml").is_file()
