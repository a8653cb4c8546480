"""SB3's constructor keywords as HIEROS hyperparameters: which keywords ``config_overrides`` sets instead, which have
no HIEROS meaning (each refused with what HIEROS uses instead), and SB3's ``net_arch`` as the actor's and critics'
sizes."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["CONFIG_ONLY", "NO_HIEROS_MEANING", "actor_critic_sizes", "refuse_keywords"]

#: hyperparameters that are set with ``config_overrides`` only (not constructor keywords)
CONFIG_ONLY = ("batch_length", "train_ratio", "imag_horizon", "n_levels", "subgoal_interval", "etbs_temperature")

#: keywords of SB3's other algorithms that have no HIEROS meaning, and what HIEROS uses instead
NO_HIEROS_MEANING = {
    "train_freq": "HIEROS updates by train_ratio (replayed steps per environment step): config_overrides="
    "{'train_ratio': ...}",
    "gradient_steps": "HIEROS updates by train_ratio (replayed steps per environment step): config_overrides="
    "{'train_ratio': ...}",
    "optimize_memory_usage": "the sequence replay stores every observation once already",
    "action_noise": "HIEROS explores with its stochastic actors (entropy bonus: config_overrides="
    "{'actor_critic': {'entropy': ...}})",
    "target_update_interval": "the slow critics follow the critics at every update: config_overrides="
    "{'actor_critic': {'slow_critic_fraction': ...}}",
    "tau": "the slow critics follow the critics at every update: config_overrides="
    "{'actor_critic': {'slow_critic_fraction': ...}}",
    "exploration_fraction": "HIEROS explores with its stochastic actors, not epsilon-greedy",
    "exploration_initial_eps": "HIEROS explores with its stochastic actors, not epsilon-greedy",
    "exploration_final_eps": "HIEROS explores with its stochastic actors, not epsilon-greedy",
    "max_grad_norm": "gradient norms are clipped per learner: config_overrides={'world_model': {'grad_clip': ...}, "
    "'actor_critic': {'grad_clip': ...}, 'subgoal': {'grad_clip': ...}}",
    "ent_coef": "the actor's entropy bonus is config_overrides={'actor_critic': {'entropy': ...}}",
    "target_entropy": "the actor's entropy bonus is config_overrides={'actor_critic': {'entropy': ...}}",
    "use_sde": "HIEROS explores with its stochastic actors (no state-dependent exploration)",
    "sde_sample_freq": "HIEROS explores with its stochastic actors (no state-dependent exploration)",
    "use_sde_at_warmup": "HIEROS explores with its stochastic actors (no state-dependent exploration)",
    "policy_delay": "the actor and the critics update together at every update",
    "target_policy_noise": "HIEROS has no target policy",
    "target_noise_clip": "HIEROS has no target policy",
    "n_steps": "HIEROS is off-policy: it updates by train_ratio, config_overrides={'train_ratio': ...}",
    "n_epochs": "HIEROS is off-policy: it updates by train_ratio, config_overrides={'train_ratio': ...}",
    "gae_lambda": "the lambda of the returns is config_overrides={'actor_critic': {'lambda_': ...}}",
    "clip_range": "HIEROS's actor is trained in imagination (REINFORCE or dynamics backpropagation), not clipped",
    "clip_range_vf": "HIEROS's actor is trained in imagination (REINFORCE or dynamics backpropagation), not clipped",
    "normalize_advantage": "advantages are normalised by their returns' scale: config_overrides="
    "{'actor_critic': {'return_normalization': 'per_term' or 'combined'}}",
    "vf_coef": "the critics have optimisers of their own: config_overrides={'actor_critic': {'critic_lr': ...}}",
    "target_kl": "HIEROS's actor is trained in imagination (REINFORCE or dynamics backpropagation), not clipped",
}


def refuse_keywords(kwargs: dict[str, Any]) -> None:
    """A clear error for hyperparameters passed as keywords that ``config_overrides`` sets or that HIEROS does not
    have, TypeError otherwise."""
    misplaced = {name: kwargs.pop(name) for name in CONFIG_ONLY if name in kwargs}
    if misplaced:
        raise ValueError(
            f"{', '.join(sorted(misplaced))}: not HIEROS constructor keywords; set them with "
            f"config_overrides={misplaced!r} (the constructor takes SB3's keywords learning_rate, buffer_size, "
            "learning_starts, batch_size and gamma; every other hyperparameter is a field of HierosConfig)"
        )
    meaningless = sorted(name for name in kwargs if name in NO_HIEROS_MEANING)
    if meaningless:
        raise ValueError(
            "; ".join(
                f"{name}: an SB3 keyword without a HIEROS meaning ({NO_HIEROS_MEANING[name]})" for name in meaningless
            )
        )
    if kwargs:
        raise TypeError(f"HIEROS got unexpected keywords {sorted(kwargs)}")


def actor_critic_sizes(net_arch: Any) -> dict[str, int]:
    """SB3's ``net_arch`` as HIEROS's actor and critic sizes (``actor_critic.units`` and ``layers``): HIEROS's actor
    and critics are MLPs on the world state, as SB3's actor and critics are MLPs on the features.

    :param net_arch: equal widths, e.g. ``[64, 64]``, or a dict of them for the actor (``pi``) and the critics
        (``qf`` / ``vf``), which must agree (HIEROS's actor and critics share their sizes)
    :return: ``{"units": width, "layers": depth}``
    """
    widths = net_arch
    if isinstance(net_arch, dict):
        lists = [list(v) if isinstance(v, list | tuple) else v for v in net_arch.values()]
        if not lists or set(net_arch) - {"pi", "qf", "vf"} or any(v != lists[0] for v in lists):
            raise ValueError(
                f"net_arch={net_arch!r}: HIEROS's actor and critics share one size; give a list, or a dict whose "
                "'pi' and 'qf' / 'vf' lists agree"
            )
        widths = lists[0]
    integers = isinstance(widths, list | tuple) and all(
        isinstance(w, int | np.integer) and not isinstance(w, bool) and w > 0 for w in widths
    )
    if not integers or not widths or len(set(widths)) != 1:
        raise ValueError(
            f"net_arch={net_arch!r}: HIEROS's actor and critics have equal hidden widths, at least one layer: give a "
            "list such as [64, 64] (or set config_overrides={'actor_critic': {'units': ..., 'layers': ...}})"
        )
    return {"units": int(widths[0]), "layers": len(widths)}
