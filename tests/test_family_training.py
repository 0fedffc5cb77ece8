"""Training over a plant family beside the catalogue, and a plant never seen met zero-shot."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from omegaconf import OmegaConf

from generalist_control.common.paths import conf_dir
from generalist_control.common.sections import as_dict, read_section
from generalist_control.data.demos import load_demos
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.evaluation.runner import evaluate
from generalist_control.generate_families import run as generate_family
from generalist_control.model.card import card_features, card_frame
from generalist_control.model.policy import Policy, load_policy
from generalist_control.plants.catalog import load_plant, tag_count
from generalist_control.reports.held_out import card_met, family_draw, judge_routes
from generalist_control.reports.routes_section import routes_lines
from generalist_control.training.family_set import FamilySet, join_demos, with_rows
from generalist_control.training.settings import FamilyTraining
from generalist_control.training.unseen_draw import UnseenDraw
from helpers import compose_cfg, net_config, tiny_train_overrides, train

#: Four drawn plants, 2 s trajectories (the tiny catalogue data's), checked over 10 s.
TINY_FAMILY = ("families.count=4", "data.duration=2.0", "families.checks.duration=10.0")
NEVER_SEEN = "magnetic_levitation"
#: Issue 50's zero-shot bars, as the unseen stage reads them (conf/unseen.yaml).
ROUTES_BAR = OmegaConf.to_container(OmegaConf.load(conf_dir() / "unseen.yaml"))["unseen"][
    "routes_bar"
]


@pytest.fixture(scope="module")
def family_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("families") / "tiny"
    generate_family(compose_cfg(*TINY_FAMILY, f"families.data_dir={out}",
                                config="generate_families"))  # fmt: skip
    return out


def test_the_family_joins_the_catalogue_with_tags_after_it(tiny_data_dir, family_dir):
    families = FamilySet.load([family_dir], tag_count())
    assert [p.tag for p in families.plants] == [25, 26, 27, 28]
    catalogue, manifest = load_demos(tiny_data_dir)
    joined, joint = families.joined(catalogue, manifest)
    fam, fam_manifest = load_demos(family_dir)
    assert len(joined.r) == len(catalogue.r) + len(fam.r)
    np.testing.assert_array_equal(joined.tag[len(catalogue.r) :], fam.tag + 25)
    assert joint["content_hash"] not in (manifest["content_hash"], fam_manifest["content_hash"])
    assert families.record() == [{"dir": str(family_dir), "name": "default", "seed": 1,
                                  "plants": 4}]  # fmt: skip


def test_train_over_a_family_and_meet_a_plant_never_seen(
    tiny_data_dir, family_dir, tmp_path, mlflow_uri
):
    """Tiny: one short epoch on two catalogue plants and four drawn ones; then zero-shot."""
    over = tiny_train_overrides(tiny_data_dir, tmp_path, mlflow_uri, "experiment=family_card",
                                f"train_families.dirs=[{family_dir}]", "trainer.max_epochs=2",
                                "+trainer.limit_train_batches=5", "dagger.start_epoch=1",
                                "dagger.every=1", "dagger.rounds=1", "dagger.sampler.rollouts=1",
                                "train_families.dagger_plants=2",
                                "train_families.closed_loop_plants=2", "logger.log_model=false",
                                "train_families.validation.count=3",
                                "closed_loop.systems=[]")  # fmt: skip
    metrics, objects = train(compose_cfg(*over))
    policy, meta = objects["policy"], objects["datamodule"].meta()
    families = objects["datamodule"].families
    assert policy.net.n_tags == 29 and set(families.names) <= set(meta["tags"])
    # the validation draw: three plants no training saw, scored zero-shot beside the others
    drawn = sorted(k for k in metrics if k.startswith("val/closed_loop/default_s2001_"))
    assert len(drawn) == 3 and not set(meta["tags"]) & {k.split("/")[-1] for k in drawn}
    assert 0 <= metrics["val/closed_loop/unseen"] <= 1
    assert np.isclose(metrics["val/closed_loop/unseen"], np.mean([metrics[k] for k in drawn]))
    scored = [k for k in metrics if k.startswith("val/closed_loop/") and "unseen" not in k]
    assert len(scored) == 2 + 2 + 3  # the two catalogue plants, closed_loop_plants, the draw
    assert np.isclose(metrics["val/closed_loop"], np.mean([metrics[k] for k in scored]))
    _, published = load_policy(objects["policy_path"])
    validated = {"dir": None, "name": "default", "seed": 2001, "plants": 3}
    assert published["families"][-1] == validated  # a report refuses to test on it:
    spec = {"family": "default", "seed": 2001, "count": 3, "checks": None, "state_draw": None}
    with pytest.raises(ValueError, match=r"trained or validated on \(seeds \[1, 2001\]\)"):
        family_draw(objects["policy_path"], spec, {"duration": 2.0}, {})
    p = families.plants[0]  # the bank holds each training plant's card
    card = card_features(p, card_frame(p, 10.0))
    np.testing.assert_allclose(policy.net.plant.cards[p.tag].numpy(), card, rtol=1e-6)
    plant = load_plant(NEVER_SEEN)
    grown, grown_meta = card_met(objects["policy_path"], plant)
    assert grown_meta["tags"][NEVER_SEEN] == grown.net.n_tags - 1 == 29
    scenarios = {"step": {"kind": "step", "amplitude": 1.0, "duration": 3.0}}
    df, _ = evaluate(PolicyRuntime(grown, grown_meta), [plant], scenarios, progress=False)
    assert set(df.controller) >= {"GC", "LQI"} and set(df.system) == {NEVER_SEEN}
    _check_an_unseen_draw(policy, meta)


def _check_an_unseen_draw(policy, meta):
    """Each drawn plant's card row from its model, its tag after the policy's."""
    node = as_dict(compose_cfg(*TINY_FAMILY, "families.count=3", "families.generator.seed=7",
                               config="generate_families").families)  # fmt: skip
    draw = UnseenDraw.draw(node, policy)
    assert all(p.name.startswith("default_s7_") for p in draw.plants)
    assert [p.tag for p in draw.plants] == [0, 1, 2]  # the draw's places
    grown, grown_meta = draw.met(policy, meta)
    assert grown.net.n_tags == policy.net.n_tags + 3
    assert [grown_meta["tags"][p.name] for p in draw.plants] == [29, 30, 31]
    for i, p in enumerate(draw.plants):
        card = card_features(p, card_frame(p, 10.0))
        np.testing.assert_allclose(grown.net.plant.cards[29 + i].numpy(), card, rtol=1e-6)
    tagged = Policy(net_config(hidden=16, experts=2, n_tags=2))  # a learned row per plant
    with pytest.raises(ValueError, match=r"\(model.plant: TagEmbedding\) cannot meet zero-shot"):
        UnseenDraw.draw(node, tagged)


def test_a_card_policy_takes_the_plant_by_its_yaml_path_in_the_runtime(
    tiny_data_dir, family_dir, tmp_path, mlflow_uri
):
    over = tiny_train_overrides(tiny_data_dir, tmp_path, mlflow_uri, "experiment=family_card",
                                f"train_families.dirs=[{family_dir}]", "dagger=null",
                                "+trainer.limit_train_batches=3", "closed_loop_val=null",
                                "monitor=val/loss", "logger.log_model=false",
                                "closed_loop.systems=[]")  # fmt: skip
    _, objects = train(compose_cfg(*over))
    rt = PolicyRuntime.load(objects["policy_path"])
    rt.reset(str(conf_dir() / "plants" / f"{NEVER_SEEN}.yaml"))
    assert np.isfinite(rt.step(np.zeros(3), 1.0))


def _figures(ise, rmse=1.0, diverged=0):
    return {"ISE_ratio": ise, "RMSE_ratio_worst": rmse, "diverged_runs": diverged}


def test_the_routes_bars_and_their_section():
    entries = {
        n: {"policies": {"card": _figures(v), "zero_shot": _figures(w)}}
        for n, v, w in (("a", 1.05, 1.2), ("b", 1.2, 1.3), ("c", 1.0, 1.1))
    }
    worst = [{"plant": "p7", "ISE_ratio": 2.0, "plant_is": "drawn: order 4"}]
    draw = {"plants": 100, "diverged_runs": 0, "diverged_plants": 0, "family": "default",
            "seed": 1001, "ISE_ratio": {"median": 1.01, "p95": 1.3, "max": float("inf")},
            "worst": worst}  # fmt: skip
    verdict = judge_routes(entries, draw, ROUTES_BAR)
    bars = verdict["bars"]
    assert bars["card_most_within"] and bars["card_all_within"] and bars["draw_median"]
    assert not bars["draw_p95"] and not verdict["pass"]  # p95 1.3 > 1.25
    assert verdict["card_over"] == ["b"] and verdict["context_over"] == ["b"]
    over = judge_routes(
        {**entries, "d": {"policies": {"card": _figures(None), "zero_shot": _figures(1.0)}}},
        None,
        ROUTES_BAR,
    )
    assert not over["bars"]["card_all_within"]  # a missing ratio (every run diverged) fails
    # in context is the tag-free policy (zero_shot), always evaluated; the card route may not be
    context_only = {n: {"policies": {"zero_shot": e["policies"]["zero_shot"]}}
                    for n, e in entries.items()}  # fmt: skip
    alone = judge_routes(context_only, None, ROUTES_BAR)  # unseen.routes=[]
    assert alone["not_run"] == ["card"] and not alone["pass"]
    assert alone["bars"] == {"context_no_divergence": True, "context_most_within": True}
    assert verdict["not_run"] == []
    lines = routes_lines({"held_out": context_only, "routes": alone}, "x")
    assert "`card` **not run** (no bars)" in lines[-2]
    assert "| `b` | n/a / n/a / n/a | 1.3 / 1 / 0 |" in lines
    page = "\n".join(routes_lines({"held_out": entries, "routes": verdict, "family_draw": draw},
                                  "reports/unseen/summary.json"))  # fmt: skip
    assert "| `b` | 1.2 / 1 / 0 | 1.3 / 1 / 0 |" in page
    assert "median 1.01, 95th percentile 1.3, worst inf" in page and "`p7`" in page
    assert "`draw_p95` **fail**" in page
    assert routes_lines({"held_out": entries}, "x") == []
    stored = {**draw, "ISE_ratio": {**draw["ISE_ratio"], "max": None},  # inf as JSON stores it
              "worst": [{**worst[0], "ISE_ratio": None}]}  # fmt: skip
    page = "\n".join(routes_lines({"held_out": entries, "routes": verdict, "family_draw": stored},
                                  "x"))  # fmt: skip
    assert "worst diverged." in page and "| `p7` | diverged | drawn: order 4 |" in page


def test_bad_family_settings_and_data_are_refused(tiny_data_dir, family_dir, tmp_path):
    with pytest.raises(ValueError, match="train_families.dirs must name at least one"):
        read_section(
            FamilyTraining,
            {"dirs": [], "dagger_plants": 1, "closed_loop_plants": 1},
            "train_families",
        )
    with pytest.raises(ValueError, match="train_families.dagger_plants must be >= 0"):
        read_section(
            FamilyTraining,
            {"dirs": ["x"], "dagger_plants": -1, "closed_loop_plants": 1},
            "train_families",
        )
    # null is "none", as the config's comments say (and as the zero-shot refusal advises)
    explicit = {"dirs": ["x"], "dagger_plants": 1, "closed_loop_plants": 1}
    read = read_section(
        FamilyTraining, {**explicit, "validation": None, "dagger_pick": None}, "train_families"
    )
    assert read.validation is None and read.dagger_pick is None
    with pytest.raises(ValueError, match="not a plant family's"):
        FamilySet.load([tiny_data_dir], 25)  # the catalogue's data: no plant_family block
    catalogue, _ = load_demos(tiny_data_dir)
    longer = dataclasses.replace(catalogue, r=np.hstack([catalogue.r, catalogue.r]))
    with pytest.raises(ValueError, match="match the catalogue's sample time and duration"):
        join_demos(catalogue, longer, 25)
    model = {"_target_": "generalist_control.model.card.CardPlant", "n_tags": 25}
    assert with_rows(model, None) is model
    assert with_rows({"plant": model}, FamilySet.load([family_dir], 25))["plant"]["n_tags"] == 29
