"""The generated results page (``make results``) and the size of the front-page docs."""

from __future__ import annotations

import csv
import io
import json
import re
import subprocess
import tarfile
from pathlib import Path
from typing import Any

import matplotlib
import pytest

from generalist_control.reports.figures import draw_figures, figure_key
from generalist_control.reports.results_page import (
    MAX_LINES,
    PAGE,
    RECIPES,
    build_page,
    main,
    render_page,
)
from generalist_control.reports.results_sections import MAX_ROWS, fmt

REPO = Path(__file__).resolve().parents[1]
RECIPE = {r.key: r for r in RECIPES}
#: What the page is made of: every recipe's reports and the folders of the ablation's tables.
INPUTS = sorted({p for r in RECIPES for p in r.files.values()} | {
    str(Path(r.files["summary"]).parent) for r in RECIPES if r.kind == "ablation"})  # fmt: skip
FIGURES = "docs/figures"


def _git(*args: str) -> bytes:
    return subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, check=True).stdout


def _committed(dest: Path, *paths: str) -> Path:
    """``paths`` (files or folders) as committed at HEAD, under ``dest`` (what git lacks: not).

    A stage that has just rewritten a report in the working tree (``make pipeline``) changes
    nothing here. Skips outside a git checkout.
    """
    try:
        _git("rev-parse", "--verify", "HEAD")
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("no git checkout here: the committed files cannot be read")
    files = _git("ls-tree", "-r", "-z", "--name-only", "HEAD", "--", *paths).split(b"\0")
    files = [f.decode() for f in files if f]
    with tarfile.open(fileobj=io.BytesIO(_git("archive", "HEAD", "--", *files))) as tar:
        tar.extractall(dest, filter="data")
    return dest


def _write(root: Path, path: str, content: Any) -> None:
    target = root / path
    target.parent.mkdir(parents=True, exist_ok=True)
    if path.endswith(".csv"):
        with target.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(content[0]))
            writer.writeheader()
            writer.writerows(content)
    else:
        target.write_text(json.dumps(content))


def _eval_summary(**extra: Any) -> dict[str, Any]:
    """A small evaluation summary.json with known figures."""
    return {
        "diverged": {"GC": {"random_steps": 2}, "LQI": {}, "GC-AW": {"saturation_0.25": 1}},
        "ratios": {
            "step": {
                "worst_ISE_ratio": 1.2345,
                "worst_ISE_system": "plant_a",
                "worst_ITAE_ratio": 2.5,
                "worst_ITAE_system": "plant_b",
                "worst_relative_ess_GC": 0.00123,
                "worst_relative_ess_system": "plant_c",
                "n_systems": 2,
            }
        },
        "tracking": {"sine": {"worst_RMSE_ratio": 1.0777, "worst_RMSE_system": "plant_d"}},
        "anti_windup": {"saturation_0.25": {"worst_ISE_ratio": 0.875, "worst_ISE_system": "e"}},
        "quality_bar": {"stable_everywhere": False, "ISE_ratio_le_1.05": False, "x": True},
        **extra,
    }


def test_the_committed_page_is_what_the_committed_reports_give(tmp_path):
    root = _committed(tmp_path, *INPUTS, PAGE)
    assert build_page(root) == (root / PAGE).read_text(), "run `make results` and commit"


def test_the_committed_figures_are_what_the_committed_tables_give(tmp_path):
    """Each linked image is committed, drawn from the committed tables by this code."""
    root = _committed(tmp_path / "head", *INPUTS, PAGE, FIGURES)
    page = (root / PAGE).read_text()
    links = re.findall(r"!\[[^]]*\]\(([^)]+)\)", page)
    assert len(links) >= 6 and all((root / "docs" / link).is_file() for link in links), links
    assert all((REPO / "docs" / link).is_file() for link in links)  # and in the working tree
    for recipe in ("ablation", "ablation-paper"):
        assert f"figures/{recipe}/gate_weights.png" in links
        tables = root / Path(RECIPE[recipe].files["summary"]).parent
        drawn = tmp_path / "drawn" / recipe
        names = draw_figures(tables, drawn)
        committed = sorted((root / FIGURES / recipe).glob("*.png"))
        assert [p.stem for p in committed] == sorted(names), "run `make results` and commit"
        for png in committed:
            assert figure_key(png) == figure_key(drawn / png.name), f"{png.name}: make results"
            software = _png_text(png).get("Software", "")
            if matplotlib.__version__ not in software:  # bytes depend on the version
                continue
            assert png.read_bytes() == (drawn / png.name).read_bytes(), png.name


def _png_text(path: Path) -> dict[str, str]:
    from PIL import Image

    with Image.open(path) as im:
        return dict(getattr(im, "text", {}))


def test_the_page_and_its_figures_are_deterministic_and_written_atomically(tmp_path, capsys):
    out = tmp_path / "results.md"
    assert main(["--out", str(out)]) == 0
    assert out.read_bytes() == build_page(REPO).encode()
    figures = {p: p.read_bytes() for p in sorted((tmp_path / "figures").rglob("*.png"))}
    assert len(figures) >= 6
    assert main(["--out", str(out), "--check"]) == 0
    out.write_text("edited by hand\n")
    assert main(["--out", str(out), "--check"]) == 1
    assert out.read_text() == "edited by hand\n"  # --check writes nothing
    gate = tmp_path / "figures" / "ablation" / "gate_weights.png"
    gate.write_bytes(b"\x89PNG not drawn from these tables")
    assert main(["--out", str(out), "--check"]) == 1
    assert f"stale: {gate}" in capsys.readouterr().out
    assert main(["--out", str(out)]) == 0  # drawn again, byte for byte
    assert {p: p.read_bytes() for p in sorted((tmp_path / "figures").rglob("*.png"))} == figures
    left = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.is_file())
    assert left == sorted(["results.md", *(str(p.relative_to(tmp_path)) for p in figures)])


def test_synthetic_reports_render_their_values_and_missing_recipes(tmp_path):
    _write(tmp_path, "reports/eval/summary.json", _eval_summary())
    scores = {"diverged": 3, "bar_passed": 1, "bar_checked": 2, "ISE_ratio": 1.2345}
    _write(
        tmp_path, "reports/eval/scores.json", {**scores, "ITAE_ratio": 2.5, "RMSE_ratio": 1.0777}
    )
    rows = [
        {"system": "plant_a", "settles": "True", "radius_GC": "0.9", "radius_LQI": "0.8"},
        {"system": "plant_b", "settles": "False", "radius_GC": "1.25", "radius_LQI": "0.5"},
    ]
    _write(tmp_path, "reports/eval/setpoint.csv", rows)
    text = build_page(tmp_path)
    assert "| default | 3 | 1.2345 | 2.5 | 1.0777 | 1/2 |" in text
    assert "| `step` | 1.2345 (plant_a) | 2.5 (plant_b) |  | 1.23e-03 (plant_c) | 0 |" in text
    assert "| `random_steps` |" not in text  # no ratios for it: only its divergences
    assert "| `sine` |  |  | 1.0777 (plant_d) |  | 0 |" in text
    assert "| `saturation_0.25`, GC-AW / LQI-AW | 0.875 (e) |" in text
    assert "1 of 3 passed: `stable_everywhere` **fail**, `ISE_ratio_le_1.05` **fail**" in text
    assert "1 of 2 plants settle" in text and "1 with a loop of spectral radius >= 1" in text
    assert "largest 1.25 (plant_b, LQI's 0.5)" in text
    assert "`models/metrics.json` is not here" in text  # a DVC output absent from a checkout
    missing = ("paper", "tag-free", "variants", "unseen", "ablation", "ablation-paper")
    for key in missing:
        assert f"| {key} | not run yet |" in text
        assert f"not run yet: `{RECIPE[key].command}`" in text
    assert text.count("not run yet: `") == len(missing)


def test_without_scores_json_the_headline_comes_from_the_summary(tmp_path):
    _write(tmp_path, "reports/eval/summary.json", _eval_summary())
    assert "| default | 3 | 1.2345 | 2.5 | 1.0777 | 1/3 |" in build_page(tmp_path)


def test_variants_and_ablation_render_their_values(tmp_path):
    bar = {"no_divergence": {"GC_diverged_runs": 0, "pass": True}}
    bar["worst_ISE_ratio"] = {"value": 1.75, "limit": 1.5, "pass": False}
    summary = {"bars": bar, "pass": False, "ratios": {"variants": {"worst_ISE_ratio": 1.75}}}
    summary["per_plant"] = {
        "p1": {"worst_GC_over_oracle": 1.75},
        "p2": {"worst_GC_over_oracle": 1.1},
    }
    summary["validation"] = {"bars": {"worst_ISE_ratio": {"value": 1.25, "pass": True}}, "seed": 7}
    _write(tmp_path, "reports/variants/summary.json", summary)
    configs = {"d=16,M=3": {"mse_mean": 0.00042}}
    claims = [
        {"claim": "final training loss, d=16, M=3", "paper": "1.02e-02", "ours": "0.0625 (s42)",
         "verdict": "does not reproduce"},
    ]  # fmt: skip
    counts = {"does not reproduce": 1}
    summary = {"configs": configs, "missing": ["M=5"], "claims": claims}
    _write(
        tmp_path, "ablation/report/default/summary.json", {**summary, "claims_verdicts": counts}
    )
    runs = [
        {"label": "d=16", "status": "ok", "hidden": "16.0", "experts": "3.0",
         "run_id": "abcdef123", "n_parameters": "12345.0", "final_train_loss": "0.0625",
         "closed_loop_diverged": "1"},
        {"label": "M=5", "status": "no run", "hidden": "", "experts": "", "run_id": "",
         "n_parameters": "", "final_train_loss": "", "closed_loop_diverged": ""},
    ]  # fmt: skip
    _write(tmp_path, "ablation/report/default/runs.csv", runs)
    text = build_page(tmp_path)
    assert "| variants | 0 | 1.75 | n/a | n/a | 1/2 |" in text
    assert "| `worst_ISE_ratio` | value 1.75, limit 1.5: **fail** | value 1.25: pass |" in text
    assert "held-out draw (seed 7)" in text and "| all bars | **fail** | not measured |" in text
    assert "Worst plants (their worst variant, test draw): p1 1.75, p2 1.1." in text
    assert "| d=16 | 16 | 3 | 12,345 | 0.0625 | 4.20e-04 | 1 | `abcdef12` |" in text
    assert "| M=5 | n/a | n/a | no run |" in text and "No run for: M=5." in text
    assert "claim by claim (1 does not reproduce; rules and notes in" in text
    row = "| final training loss, d=16, M=3 | 1.02e-02 | 0.0625 (s42) | does not reproduce |"
    assert row in text
    assert "## Ablation, the paper's recipe" in text  # the other recipe: not run yet
    assert "not run yet: `scripts/ablation.sh paper`" in text


def test_unseen_renders_each_held_out_plant_and_the_bar(tmp_path):
    def policy(ise, rmse, diverged=0, itae=1.0):
        return {"ISE_ratio": ise, "RMSE_ratio_worst": rmse, "diverged_runs": diverged,
                "ITAE_ratio": itae}  # fmt: skip

    entry = {
        "class": {
            "order": 3,
            "open_loop_unstable": True,
            "nonlinear": False,
            "non_minimum_phase": False,
            "min_damping": 0.1,
        },
        "adaptation_wall_s": 57.6,
        "demonstrations": {"windows": 19404, "dagger_windows": 7722},
        "policies": {
            "adapted": policy(0.99, 1.0108, itae=1.04),
            "zero_shot": policy(None, None, 32),
            "trained_with": policy(1.002, 1.0042),
        },
    }
    other = {**entry, "policies": {"adapted": policy(1.25, 1.0, 1, itae=2.5)}}
    bars = {"no_divergence": {"GC_diverged_runs": 1, "pass": False}}
    summary = {"held_out": {"maglev": entry, "other": other}, "bars": bars, "pass": False}
    _write(tmp_path, "reports/unseen/summary.json", summary)
    text = build_page(tmp_path)
    assert "| unseen | 1 | 1.25 | 2.5 | 1.0108 | 0/1 |" in text
    row = ("| `maglev` | order 3, unstable, zeta 0.1 | 58 | 19,404 + 7,722 | "
           "0.99 / 1.0108 / 0 | n/a / n/a / 32 | 1.002 / 1.0042 / 0 |")  # fmt: skip
    assert row in text
    assert (
        "| `other` | order 3, unstable, zeta 0.1 | 58 | 19,404 + 7,722 | 1.25 / 1 / 1 | " in text
    )
    assert "`no_divergence` GC_diverged_runs 1: **fail**; all: **fail**." in text


def test_provenance_is_shown_where_the_summary_has_it_and_not_needed(tmp_path):
    """Date, machine and run ids may leave the summaries (they go to MLflow): no gap left."""
    prov = {"date": "2026-12-10", "machine": "one H100, 16 cores", "command": "dvc repro -f"}
    _write(tmp_path, "reports/eval/summary.json", _eval_summary(provenance=prov))
    _write(tmp_path, "reports/tag_free/summary.json", _eval_summary())
    text = build_page(tmp_path)
    default, tag_free = text.split("## Default")[1], text.split("## Tag-free")[1].split("## ")[0]
    assert "- date: 2026-12-10\n- machine: one H100, 16 cores\n" in default
    assert "- recorded command: `dvc repro -f`" in default
    head = "- command: `dvc repro beyond/dvc.yaml:tag_free`\n- reports: `reports/tag_free/"
    assert head in tag_free and "date" not in tag_free and "not recorded" not in text


def test_the_page_stays_short_whatever_the_reports_hold():
    many = {f"scenario_{i}": {"worst_ISE_ratio": 1.0 + i} for i in range(3 * MAX_ROWS)}
    summary = _eval_summary(ratios=many, quality_bar={f"bar_{i}": True for i in range(50)})
    summary["tracking"] = {f"track_{i}\nwith | odd text": {} for i in range(3 * MAX_ROWS)}
    bars = {f"bar_{i}": {"value": i, "pass": True} for i in range(3 * MAX_ROWS)}
    runs = [{"label": f"d={i}", "status": "ok", "hidden": i, "experts": 3} for i in range(99)]
    setpoint = [{"system": f"p{i}", "settles": "True", "radius_GC": "0.5"} for i in range(500)]
    eval_data = {"summary": summary, "setpoint": setpoint, "training": {"epochs": 1}}
    reports = {r.key: eval_data for r in RECIPES if r.kind == "evaluation"}
    reports["tag-free"] = {**eval_data, "bar": {"diverged": [f"p{i}" for i in range(99)]}}
    reports["variants"] = {"summary": {"bars": bars, "validation": {"bars": bars}}}
    claims = [{"claim": f"claim {i}", "verdict": "reproduces"} for i in range(99)]
    ablation = {"summary": {"missing": [str(i) for i in range(99)], "claims": claims}}
    reports["ablation"] = reports["ablation-paper"] = {**ablation, "runs": runs}
    text = render_page(reports)
    assert len(text.splitlines()) <= MAX_LINES
    rows = 2 * 3 * MAX_ROWS + 1  # step and tracking scenarios, and the anti-windup one
    assert f"{rows - MAX_ROWS} more in `reports/eval/summary.json`" in text
    assert "p0, p1, p2, p3, p4 and 94 more" in text


def test_the_front_pages_are_short():
    assert len((REPO / "README.md").read_text().splitlines()) <= 150
    assert len((REPO / PAGE).read_text().splitlines()) <= MAX_LINES
    make = (REPO / "Makefile").read_text()
    assert "\nresults:" in make and "-m generalist_control.reports.results_page" in make


@pytest.mark.parametrize("recipe", RECIPES, ids=lambda r: r.key)
def test_every_recipe_names_its_summary_and_a_command(recipe):
    assert recipe.files["summary"].endswith("summary.json") and recipe.command


def test_the_readme_quotes_the_committed_evaluation(tmp_path):
    root = _committed(
        tmp_path, "README.md", "reports/eval/scores.json", "reports/eval/summary.json"
    )
    readme = (root / "README.md").read_text()
    scores = json.loads((root / "reports/eval/scores.json").read_text())
    summary = json.loads((root / "reports/eval/summary.json").read_text())
    aw = summary["anti_windup"]["saturation_0.25"]["worst_ISE_ratio"]
    for value in (scores["ISE_ratio"], scores["ITAE_ratio"], scores["RMSE_ratio"], aw):
        assert f"| {fmt(value)} (" in readme, "README's table: copy it from reports/eval"
    assert f"| GC runs diverged, every scenario | {scores['diverged']} |" in readme
    assert f"| {scores['bar_passed']} of {scores['bar_checked']} |" in readme
    assert f"| {scores['ess_ppm'] / 1e4:.3f} % (" in readme


def test_the_tag_free_bar_and_thousands_are_written_as_they_read(tmp_path):
    _write(tmp_path, "reports/tag_free/summary.json", _eval_summary())
    bar = {"met": True, "passed": 23, "plants": 25, "ise_ratio_bar": 1.1, "min_plants": 22,
           "no_divergence": True, "diverged": [], "missing": ["cstr", "unstable"]}  # fmt: skip
    _write(tmp_path, "reports/tag_free_bar/bar.json", bar)
    metrics = {"epochs": 30, "n_parameters": 56484, "val/loss": 1234.5678}
    _write(tmp_path, "models/tag_free/metrics.json", metrics)
    text = build_page(tmp_path)
    assert (
        "Tag-free bar (`reports/tag_free_bar/bar.json`): met; 23 of 25 plants within the "
        "unit-step ISE ratio 1.1 (at least 22 required); no divergence: pass; diverged: none; "
        "missed: cstr, unstable." in text
    )
    assert "30 epochs, 56,484 parameters, val/loss 1,235," in text
    assert [fmt(v) for v in (56484, 56484.0, 1234567.25, 999.5, -2500.0)] == [
        "56,484", "56,484", "1,234,567", "999.5", "-2,500"]  # fmt: skip


@pytest.mark.parametrize(
    ("path", "content", "says"),
    [
        ("reports/eval/summary.json", '{"ratios": {', "is not valid JSON"),
        ("reports/eval/summary.json", "[1, 2]", "holds a JSON list, not an object"),
        ("reports/eval/scores.json", '{"ISE_ratio": 1.0', "is not valid JSON"),
        ("reports/eval/summary.json", '{"ratios": [1, 2]}', "not the layout the page reads"),
        ("reports/unseen/summary.json", '{"held_out": {"p": {"policies": 3}}}', "not the layout"),
        ("ablation/report/paper/runs.csv", "sweep\nhidden\n", "not the layout the page reads"),
    ],
)
def test_a_malformed_report_is_named_with_the_fix_and_nothing_is_written(
    tmp_path, capsys, path, content, says
):
    root = tmp_path / "repo"
    _committed(root, *INPUTS)
    (root / path).write_text(content)
    out = tmp_path / "results.md"
    out.write_text("the page before\n")
    assert main(["--root", str(root), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("make results: ") and path in err and says in err, err
    assert "git checkout -- " in err and "or write it again with `" in err
    assert "Traceback" not in err
    assert out.read_text() == "the page before\n" and not (tmp_path / "figures").exists()
