"""The ablations of thesis section 5.3 (and the reference-compat switches) by name, as configuration changes.

Every ablation is a change of :class:`~sb3_hieros.config.HierosConfig` fields, i.e. a ``config_overrides`` dict for
:class:`~sb3_hieros.HIEROS`; :data:`ABLATIONS` names them (``docs/ablations.md`` is the table for users) and
:func:`ablation_overrides` resolves one against a preset::

    from sb3_hieros import HIEROS
    from sb3_hieros.ablations import ablation_overrides

    model = HIEROS("MlpPolicy", "CartPole-v1", preset="small", config_overrides=ablation_overrides("rssm", "small"))

``benchmarks/ablations.py`` runs HIEROS against any of them.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from sb3_hieros.config import REFERENCE_BEHAVIOUR, HierosConfig, get_preset

__all__ = [
    "ABLATIONS",
    "Ablation",
    "ablation_changes_preset",
    "ablation_config",
    "ablation_overrides",
    "merge_overrides",
]


@dataclass(frozen=True)
class Ablation:
    """One ablation: a named change of the configuration.

    :param name: the name used by ``benchmarks/ablations.py --ablation``
    :param section: thesis section (``"5.3.1"`` ... ``"5.3.12"``) or ``"reference"`` (a behaviour of the public
        reference code)
    :param description: what changes, in a few words
    :param changes: the ``config_overrides`` of the ablation given the preset's configuration (some depend on it,
        e.g. the smaller S5WM halves the preset's ``s5_layers``)
    """

    name: str
    section: str
    description: str
    changes: Callable[[HierosConfig], dict[str, Any]]


def _fixed(changes: dict[str, Any]) -> Callable[[HierosConfig], dict[str, Any]]:
    return lambda _config: copy.deepcopy(changes)


_LIST = [
    Ablation(
        "shared_world_model",
        "5.3.1",
        "one world model (level 0's) for all levels, no hierarchical imagination",
        _fixed({"hierarchical_world_models": False}),
    ),
    Ablation("rssm", "5.3.2", "DreamerV3's RSSM instead of the S5WM", _fixed({"world_model": {"kind": "rssm"}})),
    Ablation("uniform_replay", "5.3.3", "uniform replay instead of ETBS", _fixed({"replay": "uniform"})),
    Ablation(
        "reference_replay",
        "5.3.3",
        "the reference code's ETBS (index scaled by the capacity)",
        _fixed({"replay": "reference"}),
    ),
    Ablation("count_replay", "5.3.3", "count-based time-balanced replay (O(n))", _fixed({"replay": "count"})),
    *(Ablation(f"levels_{n}", "5.3.4", f"hierarchy depth {n}", _fixed({"n_levels": n})) for n in (1, 2, 3, 4)),
    Ablation(
        "deter_from_output",
        "5.3.5",
        "h_t from the S5 stack output instead of the S5 internal states (small preset: instead of its GRU state)",
        _fixed({"world_model": {"deter_from": "output"}}),
    ),
    Ablation(
        "deter_from_state",
        "5.3.5",
        "h_t read out from the S5 internal states as in the thesis (the counterpart for the small preset, whose h_t "
        "is a GRU state)",
        _fixed({"world_model": {"deter_from": "state"}}),
    ),
    Ablation(
        "last_state_only",
        "5.3.6",
        "a higher level observes only the k-th lower world state",
        _fixed({"higher_level_input": "last"}),
    ),
    Ablation(
        "small_s5",
        "5.3.7",
        "half the S5 blocks (thesis: 4 instead of 8)",
        lambda config: {"world_model": {"s5_layers": max(1, config.world_model.s5_layers // 2)}},
    ),
    Ablation(
        "decoded_subgoals",
        "5.3.8",
        "the lower actor gets the decoded subgoal instead of its code",
        _fixed({"decoded_subgoal_input": True}),
    ),
    Ablation(
        "update_subgoals",
        "5.3.9",
        "the level above re-plans the subgoal every k imagined steps",
        _fixed({"update_subgoals_in_imagination": True}),
    ),
    Ablation(
        "extrinsic_top_only",
        "5.3.10",
        "extrinsic reward for the top level only",
        _fixed({"extrinsic_reward_levels": "top"}),
    ),
    Ablation(
        "no_actor_extras",
        "5.3.11",
        "no reward / continue / prior-entropy actor inputs",
        _fixed({"actor_critic": {"actor_extras": False}}),
    ),
    Ablation("no_novelty", "5.3.12", "no novelty reward", _fixed({"actor_critic": {"novelty_weight": 0.0}})),
    Ablation(
        "with_novelty",
        "5.3.12",
        "novelty reward at the thesis' weight 0.1 (the counterpart of no_novelty for the small preset, which has none)",
        _fixed({"actor_critic": {"novelty_weight": 0.1}}),
    ),
    Ablation(
        "reference_actions",
        "reference",
        "world model trained on (z_{t-1}, a_t) as the reference code",
        _fixed({"reference": {"action_alignment": "current"}}),
    ),
    Ablation(
        "reference_advantage",
        "reference",
        "unnormalised REINFORCE advantages as the reference code",
        _fixed({"reference": {"reinforce_advantage": "raw"}}),
    ),
    Ablation(
        "reference_terminal_reward",
        "reference",
        "the reward of the final step stored as 0 as the reference code",
        _fixed({"reference": {"terminal_reward": "zeroed"}}),
    ),
    Ablation(
        "reference_compat",
        "reference",
        "all three reference behaviours together",
        _fixed({"reference": dict(REFERENCE_BEHAVIOUR)}),
    ),
]

#: Every ablation by name.
ABLATIONS: dict[str, Ablation] = {ablation.name: ablation for ablation in _LIST}


def merge_overrides(base: Mapping[str, Any], extra: Mapping[str, Any]) -> dict[str, Any]:
    """``config_overrides`` dicts merged, nested sections field by field (``extra`` wins).

    :param base: e.g. tiny network sizes
    :param extra: e.g. an ablation's changes
    :return: a new dict
    """
    merged = copy.deepcopy(dict(base))
    for key, value in extra.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = {**merged[key], **copy.deepcopy(dict(value))}
        else:
            merged[key] = copy.deepcopy(value)
    return merged


def ablation_overrides(name: str, preset: str = "paper", base: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The ``config_overrides`` of HIEROS with ablation ``name`` on top of ``preset`` and ``base``.

    :param name: a key of :data:`ABLATIONS`, or ``"hieros"`` for no ablation
    :param preset: the preset the ablation applies to (some ablations scale with it)
    :param base: overrides applied before the ablation (e.g. smaller networks); kept in the result
    :return: ``config_overrides`` for :class:`~sb3_hieros.HIEROS`
    """
    base = dict(base or {})
    if name == "hieros":
        return copy.deepcopy(base)
    if name not in ABLATIONS:
        raise ValueError(f"unknown ablation {name!r}; expected 'hieros' or one of {sorted(ABLATIONS)}")
    config = get_preset(preset).replace(**base)
    return merge_overrides(base, ABLATIONS[name].changes(config))


def ablation_config(name: str, preset: str = "paper", base: Mapping[str, Any] | None = None) -> HierosConfig:
    """The validated configuration of ablation ``name`` (raises ``ValueError`` where it cannot apply).

    :param name: see :func:`ablation_overrides`
    :param preset: preset name
    :param base: overrides applied before the ablation
    :return: the configuration
    """
    return get_preset(preset).replace(**ablation_overrides(name, preset, base))


def ablation_changes_preset(name: str, preset: str = "paper", base: Mapping[str, Any] | None = None) -> bool:
    """Whether ablation ``name`` changes the configuration of ``preset`` (with ``base``) at all.

    ``levels_2`` on the small preset (2 levels) or ``no_novelty`` on it (no novelty reward) are the preset itself.

    :param name: see :func:`ablation_overrides`
    :param preset: preset name
    :param base: overrides applied before the ablation
    :return: False where the ablation's configuration equals the preset's
    """
    return ablation_config(name, preset, base) != get_preset(preset).replace(**dict(base or {}))
