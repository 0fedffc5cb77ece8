"""Every field of a dataset's manifest is sealed by a digest checked on load (issue 36, item 3).

The content hash covers the arrays and the data config only; ``manifest_digest`` covers the
rest (``dt``, counts, per-plant facts, ...), so a hand-edited manifest is refused, naming the
file and the command that recreates the dataset. The content hash itself is unchanged.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest

from generalist_control.common.paths import GENERATE_COMMAND
from generalist_control.data.demos import CorruptDataError, content_hash, load_demos
from generalist_control.evaluation.variant_eval import TrainingDraws, check_disjoint

REFUSED = r"manifest\.json.*" + "python -m generalist_control.generate"


def _copy(src: Path, tmp_path: Path) -> Path:
    out = tmp_path / "demos"
    out.mkdir()
    for p in src.iterdir():
        (out / p.name).write_bytes(p.read_bytes())
    return out


def _edit(out: Path, change) -> None:
    manifest = json.loads((out / "manifest.json").read_text())
    change(manifest)
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")


EDITS = {
    "dt": lambda m: m.update(dt=m["dt"] * 2),  # the case
    "history": lambda m: m.update(history=m["history"] + 1),
    "a plant's tag": lambda m: m["plants"]["cstr"].update(tag=24),
    "generator": lambda m: m.update(generator="someone else"),
    "an added field": lambda m: m.update(note="hand-written"),
    "a removed field": lambda m: m.pop("windows_per_trajectory"),
    "the digest itself": lambda m: m.update(manifest_digest="sha256:" + "0" * 64),
    "no digest": lambda m: m.pop("manifest_digest"),
}


@pytest.mark.parametrize("field", list(EDITS))
def test_an_edited_manifest_is_refused(tmp_path, tiny_data_dir, field):
    out = _copy(tiny_data_dir, tmp_path)
    _edit(out, EDITS[field])
    with pytest.raises(CorruptDataError, match=REFUSED) as err:
        load_demos(out)
    assert str(out) in str(err.value) and GENERATE_COMMAND in str(err.value)


def test_a_manifest_that_is_not_json_is_refused_with_the_fix(tmp_path, tiny_data_dir):
    out = _copy(tiny_data_dir, tmp_path)
    (out / "manifest.json").write_text('{"dt": 0.05,')  # cut short
    with pytest.raises(CorruptDataError, match=r"manifest\.json is not JSON.*generate"):
        load_demos(out)
    (out / "manifest.json").write_text("[1, 2]")
    with pytest.raises(CorruptDataError, match=r"manifest\.json is not a JSON object"):
        load_demos(out)


def test_the_digest_covers_the_written_manifest_and_not_the_content_hash(tiny_data_dir):
    """The digest is SHA-256 of the other fields' canonical JSON; the content hash is still
    the arrays' and the data config's alone (same seed, same data hash)."""
    manifest = json.loads((tiny_data_dir / "manifest.json").read_text())
    body = {k: v for k, v in manifest.items() if k != "manifest_digest"}
    text = json.dumps(body, sort_keys=True, separators=(",", ":")).encode()
    assert manifest["manifest_digest"] == "sha256:" + hashlib.sha256(text).hexdigest()
    demos, loaded = load_demos(tiny_data_dir)
    assert loaded["content_hash"] == manifest["content_hash"]
    assert content_hash(demos, manifest["config"]) == manifest["content_hash"]


def test_the_variants_evaluation_reads_the_checked_manifest(tmp_path, tiny_data_dir):
    """The one other reader of manifest.json (training variants' factors) is checked too."""
    out = _copy(tiny_data_dir, tmp_path)
    _edit(out, lambda m: m.update(variants={"cstr": {"kept": []}}))
    with pytest.raises(CorruptDataError, match=REFUSED):
        check_disjoint({}, [], TrainingDraws(out, 1013, 0.25, 8, 10, range(0), 0), seed=5)
