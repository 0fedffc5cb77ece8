"""The default recipe is a learned generalist: the plant reaches the network only through the
learned tag embedding (issue 11)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from generalist_control.common.sections import as_dict
from generalist_control.model.network import GeneralistNetwork
from generalist_control.model.plant import TagEmbedding
from generalist_control.model.policy import Policy, load_policy
from generalist_control.training.settings import read_training
from helpers import compose_cfg

REPO = Path(__file__).resolve().parents[1]
#: The one trainable parameter a plant may index: the paper's learned tag embedding.
TAG_EMBEDDING = "net.plant.rows.weight"


def _indexed_by_plant(policy: Policy) -> set[str]:
    """Trainable parameters with an axis of length n_tags (a block per plant)."""
    n_tags = policy.net.n_tags
    return {name for name, p in policy.named_parameters() if p.requires_grad and n_tags in p.shape}


def _tag_only_through_embedding(net: GeneralistNetwork) -> bool:
    """Two tags whose embedding rows are equal give equal outputs on equal inputs."""
    torch.manual_seed(0)
    with torch.no_grad():
        rows = net.plant.rows.weight
        rows[1] = rows[0]
        for p in net.parameters():  # non-zero everywhere, so every path is live
            if p.abs().sum() == 0:
                p.normal_(0.0, 0.1)
        rows[1] = rows[0]
    state = torch.randn(6, net.history, net.width)
    mask = torch.ones_like(state)
    ref = torch.randn(6, net.history)
    a = net(state, mask, ref, torch.zeros(6, dtype=torch.long))
    b = net(state, mask, ref, torch.ones(6, dtype=torch.long))
    return torch.equal(a.control, b.control) and torch.equal(a.gates, b.gates)


def test_the_default_recipe_indexes_nothing_by_plant_but_the_tag_embedding():
    cfg = compose_cfg()
    policy = Policy(read_training(as_dict(cfg)).model)
    assert isinstance(policy.net.plant, TagEmbedding)
    assert _indexed_by_plant(policy) == {TAG_EMBEDDING}
    assert _tag_only_through_embedding(policy.net)


def test_the_checks_see_a_parameter_indexed_by_plant_and_a_tag_read_elsewhere():
    policy = Policy(read_training(as_dict(compose_cfg())).model)
    policy.net.extra = torch.nn.Embedding(policy.net.n_tags, 4)  # a per-plant table
    assert _indexed_by_plant(policy) == {TAG_EMBEDDING, "net.extra.weight"}
    plant = policy.net.plant
    code = plant.forward
    plant.forward = lambda s, m, r, t: (code(s, m, r, t)[0] + t[:, None].float(), None)
    assert not _tag_only_through_embedding(policy.net)


@pytest.mark.skipif(
    not (REPO / "models/policy.ckpt").is_file(),
    reason="no trained default policy here (dvc repro train, or dvc pull, makes one)",
)
def test_the_pipelines_policy_indexes_nothing_by_plant_but_the_tag_embedding():
    policy, _ = load_policy(REPO / "models/policy.ckpt")
    assert _indexed_by_plant(policy) == {TAG_EMBEDDING}
    assert _tag_only_through_embedding(policy.net)
