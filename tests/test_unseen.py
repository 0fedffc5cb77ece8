"""The held-out protocol (``beyond/dvc.yaml:unseen``): its plants, its commands, its chain."""

from __future__ import annotations

import json
import os
import shlex
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from generalist_control.common.sections import as_dict
from generalist_control.model.policy import load_policy
from generalist_control.plants.catalog import available_plants, load_plant
from generalist_control.reports import held_out
from generalist_control.reports.explore import plant_class
from generalist_control.reports.held_out import POLICIES, ROUTES, judge
from generalist_control.simulation.family_draw import read_families
from generalist_control.training.settings import read_training
from helpers import compose_cfg, run_command, tiny_train_overrides, untrained_policy

REPO = Path(__file__).resolve().parents[1]
STAGE = yaml.safe_load((REPO / "beyond" / "dvc.yaml").read_text())["stages"]["unseen"]
CONFIG = yaml.safe_load((REPO / "conf" / "unseen.yaml").read_text())
#: The adapted rows' bar, as the stage reads it (conf/unseen.yaml).
BAR = CONFIG["unseen"]["bar"]


def test_plant_class_against_hand_values():
    cstr = plant_class(load_plant("cstr"))  # zero at s = +2.82, stable poles
    assert cstr["non_minimum_phase"] and not cstr["open_loop_unstable"]
    maglev = plant_class(load_plant("magnetic_levitation"))
    assert maglev["open_loop_unstable"] and maglev["order"] == 3
    osc = plant_class(load_plant("damped_oscillator"))  # wn = 2, zeta = 0.1
    assert osc["min_damping"] == pytest.approx(0.1)
    assert plant_class(load_plant("two_tank"))["nonlinear"]
    assert plant_class(load_plant("mass_spring_damper"))["min_damping"] is None  # real poles


def test_the_held_out_plants_span_the_classes_and_each_class_stays_in_training():
    held = CONFIG["held_out"]
    assert len(held) >= 5
    trained = [n for n in available_plants() if n not in held]

    def classes(names):
        c = [plant_class(load_plant(n)) for n in names]
        return {
            "unstable": any(x["open_loop_unstable"] for x in c),
            "non-minimum-phase": any(x["non_minimum_phase"] for x in c),
            "nonlinear": any(x["nonlinear"] for x in c),
            "order 4": any(x["order"] == 4 for x in c),
            "lightly damped": any((x["min_damping"] or 1.0) < 0.2 for x in c),
        }

    assert all(classes(held).values()), classes(held)
    assert all(classes(trained).values()), classes(trained)


def test_held_out_plants_are_left_out_of_training():
    cfg = compose_cfg("systems.include=[cstr,hydraulic_actuator]", "held_out=[cstr]")
    assert read_training(as_dict(cfg)).trained_names == ["hydraulic_actuator"]
    with pytest.raises(ValueError, match=r"held_out names \['nowhere'\].*does not hold"):
        read_training(as_dict(compose_cfg("held_out=[nowhere]")))
    with pytest.raises(ValueError, match="leaves no plant of the set to train on"):
        read_training(as_dict(compose_cfg("systems.include=[cstr]", "held_out=[cstr]")))


def test_a_held_out_typo_is_refused_before_anything_is_adapted(tiny_demos, tmp_path):
    """The three policies in place: the typo is named before the first plant is adapted."""
    from generalist_control.unseen import run

    for folder in ("default", "tag_free", "with"):
        (tmp_path / "models" / folder).mkdir(parents=True)
        untrained_policy(tmp_path / "models" / folder, tiny_demos, "policy.ckpt")
    cfg = compose_cfg(
        "held_out=[damped_oscillator,nosuchplant]", f"unseen.models={tmp_path / 'models'}",
        f"unseen.trained_with={tmp_path / 'models/with/policy.ckpt'}",
        f"logger.tracking_uri=sqlite:///{tmp_path / 'mlflow.db'}", "logger.log_model=false",
        f"paths.reports_dir={tmp_path / 'reports'}", config="unseen",
    )  # fmt: skip
    with pytest.raises(ValueError, match=r"held_out names \['nosuchplant'\].*known: auv_yaw"):
        run(cfg)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["models"]
    assert not (tmp_path / "models" / "adapted").exists()


def _commands() -> list[list[str]]:
    return [shlex.split(c) for c in STAGE["cmd"].split(" && ")]


def test_the_stage_commands_write_where_the_protocol_reads():
    train_default, train_free, train_card, evaluate = _commands()
    models = CONFIG["unseen"]["models"]
    assert "--config-name" in train_default and "unseen" in train_default
    assert CONFIG["paths"]["published_dir"] == f"{models}/default"
    assert f"paths.published_dir={models}/tag_free" in train_free
    assert "experiment=tag_free" in train_free
    for folder, cmd in zip(ROUTES.values(), (train_card,), strict=True):
        assert f"experiment={folder}" in cmd and "unseen" in cmd
        assert f"paths.published_dir={models}/{folder}" in cmd
    assert evaluate == ["python", "-m", "generalist_control.unseen"]
    outs = [o if isinstance(o, str) else next(iter(o)) for o in STAGE["outs"]]
    assert {f"{models}/{f}/policy.ckpt" for f in ("default", "tag_free", *ROUTES.values())} <= set(
        outs
    )
    assert f"{models}/adapted" in outs and CONFIG["unseen"]["trained_with"] in STAGE["deps"]


#: What the tiny chain appends to each of the stage's commands.
TINY_TRAIN = (
    "systems.include=[cstr,hydraulic_actuator]", "held_out=[hydraulic_actuator]",
    "trainer.max_epochs=1", "trainer.accelerator=cpu", "trainer.enable_progress_bar=false",
    "trainer.enable_model_summary=false", "logger.log_model=false",
)  # fmt: skip
#: ... and what the family trainings add (the tiny family: 4 plants).
TINY_FAMILY = (
    "train_families.dagger_plants=2",
    "train_families.closed_loop_plants=2",
    "train_families.validation.count=2",
)
TINY_UNSEEN = (
    "held_out=[hydraulic_actuator]", "unseen.family_draw.count=3",
    "unseen.family_draw.checks={duration:10.0}",
    "adapt.epochs=2", "adapt.rounds=1", "adapt.batch_size=64",
    "logger.log_model=false", "data.duration=2.0", "data.families=null",
    "data.amplitudes.segments=[{start:1.0,stop:4.0,step:1.0}]", "evaluation.backend=torch",
    "~evaluation.scenarios",
    "+evaluation.scenarios={step:{kind:step,duration:5.0},"
    "sine:{kind:sine,amplitude:1.0,omega:0.5,y0:0.5,duration:5.0}}",
)  # fmt: skip


@pytest.mark.slow
def test_the_stage_runs_on_tiny_data(tiny_data_dir, tmp_path, mlflow_uri):
    """Tiny: the stage's own commands, in a folder of the tiny data and a tiny models/."""
    from helpers import train

    (tmp_path / "data").mkdir()
    shutil.copytree(tiny_data_dir, tmp_path / "data" / "demos")
    over = tiny_train_overrides(tiny_data_dir, tmp_path / "with", mlflow_uri,
                                "logger.log_model=false")  # fmt: skip
    _, trained = train(compose_cfg(*over))
    (tmp_path / "models").mkdir()
    shutil.copy(trained["policy_path"], tmp_path / "models" / "policy.ckpt")
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO / "src"), env.get("PYTHONPATH", "")])
    family = [sys.executable, "-m", "generalist_control.generate_families", "families.count=4",
              "data.duration=2.0", "families.checks.duration=10.0"]  # fmt: skip
    proc = run_command(family, cwd=tmp_path, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for cmd in _commands():
        tiny = TINY_UNSEEN if cmd[-1] == "generalist_control.unseen" else TINY_TRAIN
        tiny += TINY_FAMILY if any("experiment=family" in c for c in cmd) else ()
        argv = [sys.executable, *cmd[1:], *tiny]
        proc = run_command(argv, cwd=tmp_path, env=env,
                              timeout=900)  # fmt: skip
        assert proc.returncode == 0, (cmd, proc.stderr[-3000:])
    left = {p.name for p in tmp_path.iterdir()} & {"checkpoints", ".hydra", "train.log"}
    assert not left, f"the stage's commands wrote {left} into the repository's root"
    base, meta = load_policy(tmp_path / "models/unseen/default/policy.ckpt")
    assert set(meta["tags"]) == {"cstr"}
    adapted, meta = load_policy(tmp_path / "models/unseen/adapted/hydraulic_actuator/policy.ckpt")
    assert meta["tags"] == {"cstr": 10, "hydraulic_actuator": base.net.n_tags}
    df = pd.read_csv(tmp_path / "reports/unseen/metrics.csv")
    assert list(df.columns) == ["policy", "system", "scenario", "controller", "run", "metric",
                                "value"]  # fmt: skip
    assert set(df.policy) == {*POLICIES, *ROUTES}
    drawn = set(df.system) - {"hydraulic_actuator"}
    assert len(drawn) == 3 and set(df[df.system.isin(drawn)].policy) == {"card"}
    assert set(df.scenario) == {"step", "sine"}
    summary = json.loads((tmp_path / "reports/unseen/summary.json").read_text())
    entry = summary["held_out"]["hydraulic_actuator"]
    assert summary["family_draw"]["plants"] == 3 and summary["family_draw"]["seed"] == 1001
    assert set(summary["routes"]["bars"]) >= {"card_no_divergence", "draw_median",
                                              "context_no_divergence"}  # fmt: skip
    assert entry["adaptation_wall_s"] > 0 and entry["demonstrations"]["windows"] == 8 * 38
    assert entry["class"]["order"] == 3
    for label in (*POLICIES, *ROUTES):
        figures = entry["policies"][label]
        assert figures["ISE_ratio"] is None or np.isfinite(figures["ISE_ratio"]), label
        assert "RMSE_ratio_worst" in figures and "diverged_runs" in figures


def _entry(ise, rmse, diverged=0, wall=60.0):
    adapted = {"ISE_ratio": ise, "RMSE_ratio_worst": rmse, "diverged_runs": diverged}
    return {"adaptation_wall_s": wall, "policies": {"adapted": adapted}}


def test_the_bar_allows_one_plant_over_the_tight_limits_and_none_over_the_loose_one():
    good = {f"p{i}": _entry(1.0, 1.0) for i in range(4)}
    one_over = judge({**good, "x": _entry(1.2, 1.0)}, BAR)  # ISE over 1.10, under 1.5
    assert one_over["pass"] and one_over["bars"]["most_within"]["over"] == ["x"]
    two_over = judge({**good, "x": _entry(1.2, 1.0), "y": _entry(1.0, 1.3)}, BAR)
    assert not two_over["bars"]["most_within"]["pass"] and not two_over["pass"]
    assert two_over["bars"]["all_within"]["pass"]  # 1.3 <= 1.5
    loose = judge({**good, "x": _entry(1.0, 1.51)}, BAR)
    assert not loose["bars"]["all_within"]["pass"] and loose["bars"]["most_within"]["pass"]


def test_the_bar_fails_on_a_divergence_a_missing_ratio_or_a_slow_adaptation():
    good = {f"p{i}": _entry(1.0, 1.0) for i in range(4)}
    assert judge(good, BAR)["pass"]
    diverged = judge({**good, "x": _entry(1.0, 1.0, diverged=2)}, BAR)
    assert diverged["bars"]["no_divergence"]["GC_diverged_runs"] == 2 and not diverged["pass"]
    missing = judge({**good, "x": _entry(None, None)}, BAR)  # every step run diverged: no ratio
    assert missing["bars"]["all_within"]["value"] == float("inf") and not missing["pass"]
    slow = judge({**good, "x": _entry(1.0, 1.0, wall=181.0)}, BAR)
    assert not slow["bars"]["adaptation_wall_s"]["pass"]
    assert judge({**good, "x": _entry(1.0, 1.0, wall=181.0)}, {**BAR, "wall_s": 200})["pass"]


def test_the_stage_reads_its_config_once_into_settings():
    from generalist_control.unseen import read_unseen

    cfg = compose_cfg("unseen.bar.ISE_ratio=2.0", "unseen.family_draw=null", config="unseen")
    settings = read_unseen(cfg)
    assert settings.bar == {**BAR, "ISE_ratio": 2.0}  # every limit from conf/unseen.yaml
    assert settings.routes_bar == CONFIG["unseen"]["routes_bar"] and BAR["ISE_ratio"] == 1.1
    assert settings.family_draw is None and settings.routes == ("card",)
    with pytest.raises(ValueError, match=r"names \['in_context'\]: .* in context is the tag-free"):
        read_unseen(compose_cfg("unseen.routes=[card,in_context]", config="unseen"))
    with pytest.raises(ValueError, match=r"unseen.routes names \['card_x'\]: the routes are"):
        read_unseen(compose_cfg("unseen.routes=[card_x]", config="unseen"))
    assert settings.models == Path("models/unseen") and settings.evaluation.scenarios
    assert settings.trained_with == Path("models/policy.ckpt")


def test_the_routes_named_are_the_policies_required(tmp_path):
    from generalist_control.unseen import read_unseen

    for folder in ("default", "tag_free"):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "policy.ckpt").touch()
    (tmp_path / "with.ckpt").touch()
    over = (f"unseen.models={tmp_path}", f"unseen.trained_with={tmp_path / 'with.ckpt'}")
    settings = read_unseen(compose_cfg(*over, "unseen.routes=[]", config="unseen"))
    assert held_out._paths(settings)[1] == {}  # no route: no family training needed
    settings = read_unseen(compose_cfg(*over, "unseen.routes=[card]", config="unseen"))
    missing = r"no card policy at .*family_card/policy.ckpt; make it with: dvc repro beyond"
    with pytest.raises(FileNotFoundError, match=missing + r"/dvc.yaml:unseen \(its family"):
        held_out._paths(settings)
    (tmp_path / "family_card").mkdir()
    (tmp_path / "family_card" / "policy.ckpt").touch()
    assert set(held_out._paths(settings)[1]) == {"card"}


def test_a_family_draw_of_a_family_file_with_a_defaults_list_composes_it():
    """``unseen.family_draw.family: heldout``: its file extends ``default`` (Hydra's defaults
    list), which a plain YAML load left out ("must name a plant family")."""
    spec = {"family": "heldout", "seed": 7, "checks": None}
    node = held_out._family_node(spec, {"duration": 2.0})
    default = yaml.safe_load((REPO / "conf/families/default.yaml").read_text())
    assert node["generator"]["_target_"] == default["generator"]["_target_"]
    assert node["generator"]["seed"] == 7 and node["count"] == 200  # the spec's, heldout's
    assert node["checks"]["duration"] == 2.0  # ${data.duration}
    family, _ = read_families(node)
    assert family.seed == 7
