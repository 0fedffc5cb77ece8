"""The network's config: its keys, their defaults and checks (:func:`network_config`).

A checkpoint stores the completed config as a plain ``dict``;
:class:`~generalist_control.model.network.GeneralistNetwork` is built from it.
"""

from __future__ import annotations

from typing import Any

from generalist_control.common.schema import require_int, require_switch
from generalist_control.plants.plant import MAX_ORDER

__all__ = ["MODEL_DEFAULTS", "input_width", "law_history", "network_config"]


#: Network config keys and defaults: ``hidden`` (d), ``heads`` (N_h), ``stride`` (tau),
#: ``history`` (T_h), ``horizon`` (K), ``experts`` (M), ``n_tags``, ``state_dim`` (n_max),
#: ``window_scale`` (0 or 1: per-window amplitude scaling in
#: :class:`~generalist_control.model.policy.Policy`; 0 is the paper's recipe), ``linear_head``
#: (0 or 1: add a per-tag linear map of the window to the output; 0 is the paper's),
#: ``integral`` (0 or 1: the window's state carries one more channel, the integral of the
#: tracking error that the LQI expert itself integrates; 0 is the paper's),
#: ``linear_samples`` (how many of the newest samples the linear head sees; 0, the default, is
#: the whole window; 1 with ``integral``, where the LQI law is linear in the newest
#: augmented state alone), ``linear_skip`` (0 or 1: a linear map of those samples added to
#: the output, its gains computed from the learned tag embedding by one shared linear
#: layer: the plant enters only through the embedding; 0 is the paper's), ``tag_free`` (0 or
#: 1: the network never receives the plant's identity, one shared embedding row replaces
#: the tag), ``unknown_tag`` (0 or 1: the embedding has one more row, index ``n_tags``, the
#: "tag withheld" that tag dropout trains; see :class:`~generalist_control.model.policy.Policy`)
#: and ``history_context`` (0 or 1: the skip path's gains are computed from the embedding
#: plus a learned projection of the window's summary, so the plant can be inferred from its
#: history; 0 is the default recipe) and ``control_history`` (0 or 1: the window carries one
#: more channel, the control applied one sample earlier, which only an identifier LSTM sees,
#: whose state joins the skip gains' context, so a state change can be read against the
#: control that caused it; needs ``linear_skip`` and ``history_context``; 0 is the default)
#: and ``skip_gain_scale`` (0 or 1: the skip gains are multiplied by ``exp(s)``, ``s`` a
#: learned scalar function of their context, so the gains can move over orders of
#: magnitude; needs ``linear_skip``; 0 is the default) and ``identity_head`` (0 or 1: a linear
#: read-out of the plant from the skip gains' context, trained against the tag by
#: ``model.identity_loss``; needs ``history_context``; set by that weight, not directly)
#: and ``infer_tag`` (0 or 1, with ``tag_free``: the embedding keeps a row per plant and the
#: network weighs them by the identity head's softmax, read from the identifier's state, so
#: the plant reaches the law only through the embedding of the plant it infers) and
#: ``transition_models`` (0 or 1, with ``transition_identifier`` and ``infer_tag``: each plant's
#: linear one-step model, computed from its embedding row, is weighed against the window's
#: transitions and its evidence joins the identity logits; see
#: :mod:`~generalist_control.model.identifier`) and ``transition_input_gain`` (0 or 1, with
#: ``transition_models``: each model's input column is scaled by the gain within
#: :data:`~generalist_control.model.identifier.INPUT_GAIN` that fits the window best, so an
#: actuator whose gain is off leaves the plant its evidence) and ``transition_input_lag`` and
#: ``transition_input_offset`` (0 or 1, with ``transition_models``: each model's control is
#: the best-fitting mix with the previous control, :data:`~generalist_control.model.
#: identifier.INPUT_LAGS`, or gains a fitted constant input disturbance).
MODEL_DEFAULTS: dict[str, int] = {
    "hidden": 32,
    "heads": 3,
    "stride": 2,
    "history": 8,
    "horizon": 3,
    "experts": 3,
    "n_tags": 25,
    "state_dim": MAX_ORDER,
    "window_scale": 0,
    "linear_head": 0,
    "integral": 0,
    "linear_samples": 0,
    "linear_skip": 0,
    "tag_free": 0,
    "unknown_tag": 0,
    "history_context": 0,
    "control_history": 0,
    "skip_gain_scale": 0,
    "identity_head": 0,
    "infer_tag": 0,
    "law_history": 0,
    "transition_identifier": 0,
    "transition_models": 0,
    "transition_input_gain": 0,
    "transition_input_lag": 0,
    "transition_input_offset": 0,
}

#: Keys that are switches (0 or 1) rather than sizes.
_SWITCHES = (
    "window_scale",
    "linear_head",
    "integral",
    "linear_skip",
    "tag_free",
    "unknown_tag",
    "history_context",
    "control_history",
    "skip_gain_scale",
    "identity_head",
    "infer_tag",
    "transition_identifier",
    "transition_models",
    "transition_input_gain",
    "transition_input_lag",
    "transition_input_offset",
)

#: Where a network key is set in the training config, when not at ``model.<key>``.
_CONFIG_KEYS = {"experts": "experts", "history": "data.history", "horizon": "data.horizon"}


def input_width(config: dict[str, int]) -> int:
    """Width of the state input per step: ``state_dim`` (+1 each: integral, previous control)."""
    extra = int(config.get("integral", 0)) + int(config.get("control_history", 0))
    return int(config["state_dim"]) + extra


def law_history(config: dict[str, int]) -> int:
    """Samples of the window the law reads: ``law_history``, or the whole ``history``."""
    return int(config.get("law_history", 0)) or int(config["history"])


def network_config(**kwargs: Any) -> dict[str, int]:
    """Complete and check a network config; a plain ``dict`` (checkpoints store it as is).

    Values are taken as they are, never rounded: a size must be an integer (a float, even
    ``32.0``, a boolean or a string is refused), a switch a boolean or 0 or 1.

    Raises
    ------
    ValueError
        If a key is unknown, a size is not a positive integer (``linear_samples``: not
        negative), a switch is not 0 or 1, or ``hidden`` is odd; the message names the
        config key (``model.hidden``, ``experts``, ``data.history``), the value and its type.
    """
    unknown = set(kwargs) - set(MODEL_DEFAULTS)
    if unknown:
        raise ValueError(
            f"unknown model config keys {sorted(unknown)}; known: {sorted(MODEL_DEFAULTS)}"
        )
    cfg: dict[str, int] = {}
    for key, default in MODEL_DEFAULTS.items():
        value, name = kwargs.get(key, default), _CONFIG_KEYS.get(key, f"model.{key}")
        if key in _SWITCHES:
            cfg[key] = require_switch(name, value)
        else:
            minimum = 0 if key in ("linear_samples", "law_history") else 1
            cfg[key] = require_int(name, value, minimum=minimum)
    for key in ("law_history", "linear_samples"):
        if cfg[key] > cfg["history"]:
            raise ValueError(
                f"model.{key} ({cfg[key]}) exceeds the history (data.history = "
                f"{cfg['history']}): lower it, or lengthen data.history"
            )
    if cfg["linear_samples"] > law_history(cfg):
        raise ValueError(
            f"model.linear_samples ({cfg['linear_samples']}) exceeds the samples the law "
            f"reads (model.law_history = {cfg['law_history']})"
        )
    _check_combinations(cfg)
    if cfg["hidden"] % 2:
        raise ValueError(f"model.hidden must be even (encoders give hidden // 2), got {cfg}")
    return cfg


#: A switch, the switches it needs, and the message when one is off.
_NEEDS = (
    (
        "control_history",
        ("linear_skip", "history_context"),
        "model.control_history feeds the skip path's gains (model.linear_skip and "
        "model.history_context): turn those on, or control_history off",
    ),
    (
        "skip_gain_scale",
        ("linear_skip",),
        "model.skip_gain_scale scales the skip path's gains: turn model.linear_skip on, "
        "or skip_gain_scale off",
    ),
    (
        "identity_head",
        ("linear_skip", "history_context"),
        "model.identity_loss reads the plant from the skip gains' context (model."
        "linear_skip and model.history_context): turn those on, or identity_loss to 0",
    ),
    (
        "infer_tag",
        ("tag_free", "identity_head", "control_history"),
        "model.infer_tag infers the tag a tag-free network is not given, from the "
        "identifier (model.control_history) by the identity head (model.identity_loss > 0):"
        " set model.tag_free=true, model.control_history=true and model.identity_loss > 0",
    ),
    (
        "transition_identifier",
        ("control_history",),
        "model.transition_identifier reads each state change against the control that "
        "caused it (model.control_history): turn control_history on, or the switch off",
    ),
    (
        "transition_models",
        ("transition_identifier", "infer_tag"),
        "model.transition_models weighs each plant's one-step model in the transition "
        "identifier for the inferred tag: set model.transition_identifier=true and "
        "model.infer_tag=true, or the switch off",
    ),
    (
        "transition_input_gain",
        ("transition_models",),
        "model.transition_input_gain fits an input gain to each plant's one-step model "
        "(model.transition_models): turn transition_models on, or the switch off",
    ),
    (
        "transition_input_lag",
        ("transition_models",),
        "model.transition_input_lag fits an input lag to each plant's one-step model "
        "(model.transition_models): turn transition_models on, or the switch off",
    ),
    (
        "transition_input_offset",
        ("transition_models",),
        "model.transition_input_offset fits an input offset to each plant's one-step model "
        "(model.transition_models): turn transition_models on, or the switch off",
    ),
)


def _check_combinations(cfg: dict[str, int]) -> None:
    """Refuse switches that contradict each other or miss what they need."""
    if cfg["tag_free"] and cfg["linear_head"]:
        raise ValueError(
            "model.linear_head is a table of gains per tag and model.tag_free withholds the "
            "tag: turn one of them off"
        )
    for switch, needs, message in _NEEDS:
        if cfg[switch] and not all(cfg[k] for k in needs):
            raise ValueError(message)
