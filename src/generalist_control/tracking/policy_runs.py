"""The run that wrote a policy file, found by the file's hash.

A policy file holds no run id, so that the same training writes the same bytes (and
``dvc repro`` leaves ``dvc.lock`` as it was); the run that wrote it carries its hash as a tag.
"""

from __future__ import annotations

__all__ = ["POLICY_HASH_TAG", "find_training_run"]

#: The tag that names the policy file a run wrote, by its hash (``policy_sha256``).
POLICY_HASH_TAG = "policy.sha256"


def find_training_run(sha256: str) -> str | None:
    """The newest finished run that wrote the policy ``sha256`` (tag :data:`POLICY_HASH_TAG`)."""
    import mlflow

    runs = mlflow.search_runs(
        search_all_experiments=True,
        filter_string=f"tags.`{POLICY_HASH_TAG}` = '{sha256}' and attributes.status = 'FINISHED'",
        order_by=["attributes.start_time DESC"],
        max_results=1,
        output_format="list",
    )
    return runs[0].info.run_id if runs else None
