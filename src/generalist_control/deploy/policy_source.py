"""Where a policy comes from: a local file, or an MLflow run or registered model."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

from generalist_control.common.paths import TRAIN_COMMAND
from generalist_control.model.policy import POLICY_FILE

__all__ = ["resolve"]


def resolve(source: str | Path) -> Path:
    """A local policy file for a path or an MLflow URI (``runs:/...``, ``models:/...``).

    An MLflow URI's plain ``policy.ckpt`` (never the pickled model: loading stays
    ``weights_only``) is downloaded into a temporary folder removed at exit.
    """
    text = str(source)
    if "://" not in text and not text.startswith(("runs:/", "models:/")):
        path = Path(text)
        if not path.is_file():
            raise FileNotFoundError(f"no policy at '{path}'. Train one with: {TRAIN_COMMAND}")
        return path
    import mlflow  # optional and heavy: only for runs:/ and models:/ sources
    from mlflow.tracking import MlflowClient

    if text.startswith("models:/"):
        name, _, version = text[len("models:/") :].partition("/")
        mv = MlflowClient().get_model_version(name, version or "1")
        text = f"runs:/{mv.run_id}/policy/{POLICY_FILE}"
    elif text.startswith("runs:/") and "/" not in text[len("runs:/") :].strip("/"):
        text = text.rstrip("/") + "/policy"  # a bare run: its policy folder
    fetched = tempfile.mkdtemp(prefix="gc-policy-")
    atexit.register(shutil.rmtree, fetched, True)  # removed when the process ends
    local = Path(mlflow.artifacts.download_artifacts(artifact_uri=text, dst_path=fetched))
    if local.is_dir():
        found = sorted(local.rglob(POLICY_FILE))
        if not found:
            raise FileNotFoundError(f"no {POLICY_FILE} among the artifacts of '{source}'")
        local = found[0]
    return local
