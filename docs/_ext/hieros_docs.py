"""Sphinx extension of the sb3-hieros docs: the ``hyperparameters`` directive.

``hyperparameters`` renders one table per configuration section (``HierosConfig`` itself, then ``world_model``,
``actor_critic``, ``subgoal``, ``reference``) with every field, its value in the ``paper`` and ``small`` presets, the
thesis section it comes from, and its meaning, taken from the ``:param:`` line of the section's docstring. The values
are read from :func:`sb3_hieros.get_preset`, so the table cannot fall behind the code; a field without an entry in
:data:`THESIS` stops the build.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any

from docutils import nodes
from sphinx.application import Sphinx
from sphinx.util.docutils import SphinxDirective

#: Field (``section.name``, or ``name`` for top-level fields) -> where the thesis (Mattes 2023) describes it and, for
#: values the thesis does not give, where the value comes from.
THESIS: dict[str, str] = {
    "n_levels": "4.3, table 4.6.3; ablation 5.3.4",
    "subgoal_interval": "4.3, table 4.6.3",
    "batch_size": "table 4.6.3",
    "batch_length": "table 4.6.3 (trajectory length)",
    "imag_horizon": "4.4.3, table 4.6.3",
    "imag_start_fraction": "4.4.3 (1.0 as in the thesis)",
    "train_ratio": "4.6 (value: public code)",
    "world_model_updates": "Algorithm 2 (1 as in the thesis)",
    "buffer_size": "4.6 (value: public code)",
    "learning_starts": "4.6 (value: public code)",
    "actor_learning_starts": "not in the thesis (0: the actors start with the world models)",
    "etbs_temperature": "eq. 4.21, table 4.6.3",
    "replay": "4.5; ablation 5.3.3",
    "replay_context": "not in the thesis (DreamerV3's replay context)",
    "hierarchical_world_models": "4.3; ablation 5.3.1",
    "higher_level_input": "4.3; ablation 5.3.6",
    "decoded_subgoal_input": "ablation 5.3.8",
    "update_subgoals_in_imagination": "ablation 5.3.9",
    "extrinsic_reward_levels": "ablation 5.3.10",
    "world_model.kind": "4.4; ablation 5.3.2",
    "world_model.s5_layers": "4.4.2, table 4.6.3; ablation 5.3.7",
    "world_model.s5_model_dim": "4.4.2, table 4.6.3",
    "world_model.s5_state_dim": "4.4.2, table 4.6.3",
    "world_model.s5_hippo_blocks": "4.4.2, table 4.6.3",
    "world_model.dropout": "4.4.2 (value: public code)",
    "world_model.deter_dim": "4.4, table 4.6.3",
    "world_model.deter_from": "4.4.2; ablation 5.3.5",
    "world_model.action_input": "4.4.2 (joint); separate: later DreamerV3 releases",
    "world_model.posterior": "4.4.2 (observation, S5WM); state: DreamerV3's RSSM",
    "world_model.stoch_groups": "4.4, table 4.6.3 (z_t 32x32)",
    "world_model.stoch_classes": "4.4, table 4.6.3 (z_t 32x32)",
    "world_model.hidden": "4.4 (value: public code)",
    "world_model.cnn_depth": "4.4 (value: public code)",
    "world_model.image_shift": "not in the thesis or DreamerV3 (DrQ/RAD random shifts; off)",
    "world_model.mlp_units": "4.4 (value: public code)",
    "world_model.mlp_layers": "4.4 (value: public code)",
    "world_model.head_units": "4.4, table 4.6.3 (MLP units)",
    "world_model.head_layers": "4.4 (value: public code)",
    "world_model.unimix": "4.4 (value: DreamerV3)",
    "world_model.reward_scale": "eq. 4.11 (weight 1 in the thesis and DreamerV3)",
    "world_model.reward_overshoot": "not in the thesis or DreamerV3 (open-loop reward prediction; off)",
    "world_model.prior_decoder_scale": "not in the thesis or DreamerV3 (observation decoded from the prior; off)",
    "world_model.dyn_scale": "eq. 4.10, table 4.6.3",
    "world_model.rep_scale": "eq. 4.10, table 4.6.3",
    "world_model.free_bits": "eq. 4.12, 4.13",
    "world_model.lr": "4.4.1, table 4.6.3",
    "world_model.eps": "value: public code",
    "world_model.grad_clip": "value: public code",
    "world_model.weight_decay": "table 4.6.3",
    "world_model.warmup": "table 4.6.3",
    "actor_critic.units": "4.3.2, table 4.6.3 (MLP units)",
    "actor_critic.layers": "4.3.2 (value: public code)",
    "actor_critic.discount": "4.3.2 (value: public code)",
    "actor_critic.lambda_": "4.3.2 (value: public code)",
    "actor_critic.entropy": "eq. 4.9",
    "actor_critic.unimix": "4.3.2 (value: DreamerV3)",
    "actor_critic.extrinsic_weight": "eq. 4.3, table 4.6.3",
    "actor_critic.subgoal_weight": "eq. 4.3, table 4.6.3",
    "actor_critic.novelty_weight": "eq. 4.3, table 4.6.3; ablation 5.3.12",
    "actor_critic.actor_extras": "eq. 4.6; ablation 5.3.11",
    "actor_critic.imag_gradient": "4.3.2",
    "actor_critic.actor_lr": "value: public code",
    "actor_critic.critic_lr": "value: public code",
    "actor_critic.eps": "value: public code",
    "actor_critic.grad_clip": "value: public code",
    "actor_critic.slow_critic_fraction": "4.3.2 (value: public code)",
    "actor_critic.return_normalization": "4.3.2, eq. 4.3 (not in the thesis table)",
    "actor_critic.value_gradient": "not in the thesis (REINFORCE there; value: DreamerV3)",
    "actor_critic.return_critic": "4.3.2, eq. 4.9 (slow baseline); default: DreamerV3's fast critic",
    "actor_critic.replay_value_loss": "not in the thesis (critics on imagination only; value: later DreamerV3)",
    "subgoal.n_cat": "4.3.1, table 4.6.3 (subgoal shape 8x8)",
    "subgoal.n_classes": "4.3.1, table 4.6.3 (subgoal shape 8x8)",
    "subgoal.units": "4.3.1, table 4.6.3 (MLP units)",
    "subgoal.layers": "4.3.1 (value: public code)",
    "subgoal.beta": "eq. 4.2, table 4.6.3",
    "subgoal.lr": "table 4.6.3 (learning rate)",
    "subgoal.eps": "value: public code",
    "subgoal.grad_clip": "value: public code",
    "reference.action_alignment": "public code's behaviour, off by default",
    "reference.reinforce_advantage": "public code's behaviour, off by default",
    "reference.terminal_reward": "public code's behaviour, off by default",
}

_ROLE = re.compile(r":[a-z:]+:`~?([^`]+)`")


def param_docs(cls: type) -> dict[str, str]:
    """``name -> text`` of the ``:param name:`` lines (with their continuation lines) of a class docstring.

    :param cls: a documented class
    :return: the descriptions
    """
    docs: dict[str, str] = {}
    current: str | None = None
    for line in (cls.__doc__ or "").splitlines():
        match = re.match(r"\s*:param (\w+):\s*(.*)", line)
        if match:
            current = match.group(1)
            docs[current] = match.group(2)
        elif current is not None and line.strip() and not line.strip().startswith(":"):
            docs[current] += " " + line.strip()
        else:
            current = None
    return docs


def _inline(text: str) -> list[nodes.Node]:
    """Plain text with ````code```` and ``:role:`target``` turned into literal nodes."""
    text = _ROLE.sub(lambda m: f"``{m.group(1).split('.')[-1]}``", text)
    parts = text.split("``")
    return [nodes.literal(part, part) if i % 2 else nodes.Text(part) for i, part in enumerate(parts) if part]


def _value(value: Any) -> str:
    return repr(value) if isinstance(value, str) else f"{value:g}" if isinstance(value, float) else str(value)


def _table(rows: list[list[list[nodes.Node]]], widths: list[int]) -> nodes.table:
    table = nodes.table(classes=["longtable"])
    group = nodes.tgroup(cols=len(widths))
    table += group
    group.extend(nodes.colspec(colwidth=width) for width in widths)
    head, body = nodes.thead(), nodes.tbody()
    group += head
    group += body
    for index, cells in enumerate(rows):
        row = nodes.row()
        for cell in cells:
            entry = nodes.entry()
            entry += nodes.paragraph("", "", *cell)
            row += entry
        (head if index == 0 else body).append(row)
    return table


class HyperparametersDirective(SphinxDirective):
    """``.. hyperparameters::``: every field of the configuration, per section, paper and small values side by side."""

    def run(self) -> list[nodes.Node]:
        from sb3_hieros import HierosConfig, get_preset

        paper, small = get_preset("paper"), get_preset("small")
        sections: list[tuple[str, type, Any, Any]] = [("", HierosConfig, paper, small)]
        for field in dataclasses.fields(HierosConfig):
            value = getattr(paper, field.name)
            if dataclasses.is_dataclass(value):
                sections.append((field.name, type(value), value, getattr(small, field.name)))
        result: list[nodes.Node] = []
        missing = []
        for name, cls, paper_section, small_section in sections:
            docs = param_docs(cls)
            header = [[nodes.Text(text)] for text in ("field", "paper", "small", "thesis", "meaning")]
            rows = [header]
            for field in dataclasses.fields(cls):
                paper_value = getattr(paper_section, field.name)
                if dataclasses.is_dataclass(paper_value):
                    continue  # a section: its own table
                key = f"{name}.{field.name}" if name else field.name
                if key not in THESIS:
                    missing.append(key)
                    continue
                small_value = getattr(small_section, field.name)
                changed = small_value != paper_value
                small_text = _value(small_value)
                rows.append(
                    [
                        [nodes.literal(key, key)],
                        [nodes.Text(_value(paper_value))],
                        [nodes.strong(small_text, small_text) if changed else nodes.Text(small_text)],
                        [nodes.Text(THESIS[key])],
                        _inline(docs.get(field.name, "")),
                    ]
                )
            title = f"{name} ({cls.__name__})" if name else f"top level ({cls.__name__})"
            section = nodes.rubric(title, title)
            result += [section, _table(rows, [22, 9, 9, 20, 50])]
        if missing:
            raise self.error(f"hyperparameters: no thesis section for {missing}; add them to THESIS in {__file__}")
        return result


def setup(app: Sphinx) -> dict[str, Any]:
    app.add_directive("hyperparameters", HyperparametersDirective)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
