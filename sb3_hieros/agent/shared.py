"""Ablation 5.3.1: one world model for the whole hierarchy, i.e. HIEROS without hierarchical imagination.

With ``HierosConfig.hierarchical_world_models=False`` only level 0 is a full
:class:`~sb3_hieros.agent.subactor.Subactor` (world model, actor-critic, subgoal autoencoder). Every level i >= 1 is a
:class:`SharedLevel`: an actor-critic and a subgoal autoencoder without a world model (thesis 5.3.1: "a hierarchy of
subactors that uses only one world model", Director-like):

* **Observation.** Level i observes the last ``k**i`` world states ``[h, z]`` of level 0's world model, concatenated
  (thesis 5.3.1: "k^i consecutive world model states"), or only the newest of them with
  ``higher_level_input="last"``. Its actor and critics also see the scalar extras of eq. 4.6 (reward, continue and
  prior entropy of level 0's current state) and, below the top, the subgoal from level i+1.
* **Subgoals.** All subgoals live in level 0's h space: the subgoal level i+1 gives to level i is decoded by level i's
  autoencoder, which is trained on level 0's h. Level i's subgoal reward is the max-cosine of level 0's h and that
  decoded subgoal; its novelty reward is its autoencoder's reconstruction error of level 0's h.
* **Training** (:func:`train_shared_hierarchy`, called for every level-0 update; all levels train at every update).
  One world-model step of level 0 on the sampled chunk, then one *joint* imagination in level 0's world model from
  all B*T posterior states: at imagined step t every level i with ``t % k**i == 0`` acts (top-down) on its window
  of the last ``k**i`` level-0 states, so the subgoals change during imagination as they do when acting. The
  windows of the start states come from the chunk's posterior states (zero before the chunk's first row and before
  an episode start in the chunk, as when acting after a reset). Level i's trajectory is the imagined trajectory at
  every ``k**i``-th step, ``M = imag_horizon // k**i`` steps long: its extrinsic reward for step m is the sum of level
  0's predicted rewards over the ``k**i`` imagined steps, its continue the product of their continue probabilities,
  and its subgoal and novelty rewards are taken at the arriving state. Each level then makes its own actor, critic
  and autoencoder steps (:meth:`~sb3_hieros.agent.actor_critic.ActorCritic.loss`).

Levels i >= 1 have no replay of their own (nothing is stored for them) and are not trained from replayed subgoals.
The reference code's version of this ablation crashes (research note 8.9); its joint imagination conditions the
higher levels on the current level-0 state only, where this one follows the thesis' k**i states.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch as th
from gymnasium import spaces
from torch import nn

from sb3_hieros.agent.actor_critic import actor_input, actor_input_dim
from sb3_hieros.agent.subactor import (
    Subactor,
    imagination_start_indices,
    learn_from_imagination,
    level_actor_critic,
    level_optimizers,
    metric_floats,
    subgoal_space,
)
from sb3_hieros.agent.subgoal import SubgoalAutoencoder, max_cosine_subgoal_reward, novelty_reward
from sb3_hieros.agent.world_model import LatentState
from sb3_hieros.buffers import SequenceSamples
from sb3_hieros.config import HierosConfig

__all__ = ["SharedLevel", "start_windows", "train_shared_hierarchy"]


class SharedLevel(nn.Module):
    """Level i >= 1 of a hierarchy with one shared world model (ablation 5.3.1): actor-critic and subgoal
    autoencoder, no world model.

    :param state_dim: size D + G*K of one level-0 world state ``[h, z]``
    :param h_dim: size D of level 0's h (the autoencoder's and the decoded subgoals' space)
    :param stoch_dim: size G*K of level 0's z
    :param window: number of level-0 states observed (``k**i``, or 1 for ``higher_level_input="last"``)
    :param config: hyperparameters (actor-critic and subgoal sections, reward switches)
    :param level: index i >= 1
    :param subgoal_input: False for the top level (no subgoal input, no subgoal reward)
    :param decoded_subgoal_input: feed the decoded subgoal instead of the code (ablation 5.3.8)
    """

    def __init__(
        self,
        state_dim: int,
        h_dim: int,
        stoch_dim: int,
        window: int,
        config: HierosConfig,
        level: int,
        subgoal_input: bool,
        decoded_subgoal_input: bool = False,
    ) -> None:
        super().__init__()
        if isinstance(level, bool) or not isinstance(level, int) or level < 1:
            raise ValueError(f"level must be an int >= 1 (level 0 is a Subactor), got {level!r}")
        for name, value in (("state_dim", state_dim), ("h_dim", h_dim), ("stoch_dim", stoch_dim), ("window", window)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        if not stoch_dim < state_dim:
            raise ValueError(f"stoch_dim ({stoch_dim}) must be smaller than state_dim ({state_dim})")
        ac, sg = config.actor_critic, config.subgoal
        self.config = config
        self.level = level
        self.window = window
        self.state_dim = state_dim
        self.h_dim = h_dim
        self.stoch_dim = stoch_dim
        self.subgoal_input = bool(subgoal_input)
        self.decoded_subgoal_input = bool(decoded_subgoal_input) and self.subgoal_input
        self.observation_space = spaces.Box(-np.inf, np.inf, (window * state_dim,), np.float32)
        self.action_space = subgoal_space(sg)
        self.action_kind = "discrete"
        self.action_groups = sg.n_cat
        self.action_classes = sg.n_classes
        self.action_dim = sg.n_cat * sg.n_classes
        self.subgoal_dim = sg.n_cat * sg.n_classes
        self.imag_gradient = "reinforce"  # subgoals are categorical
        self.autoencoder = SubgoalAutoencoder(h_dim, sg.n_cat, sg.n_classes, sg.units, sg.layers, sg.beta)
        goal_feat = (h_dim if self.decoded_subgoal_input else self.subgoal_dim) if self.subgoal_input else 0
        obs_dim = window * state_dim
        self.feat_dim = actor_input_dim(obs_dim - stoch_dim, stoch_dim, goal_feat, ac.actor_extras)
        self.actor_critic = level_actor_critic(
            self.feat_dim, "discrete", sg.n_classes, sg.n_cat, "reinforce", config, self.subgoal_input
        )
        self.actor_optimizer, self.critic_optimizer, self.ae_optimizer = level_optimizers(
            self.actor_critic, self.autoencoder, config
        )

    @property
    def reward_terms(self) -> tuple[str, ...]:
        """Reward terms with a critic (weight > 0), in the order of eq. 4.3."""
        return self.actor_critic.active_terms

    @property
    def optimizers(self) -> dict[str, th.optim.Optimizer]:
        """The three optimisers by name: ``actor``, ``critic``, ``autoencoder``."""
        return {"actor": self.actor_optimizer, "critic": self.critic_optimizer, "autoencoder": self.ae_optimizer}

    def subgoal_space(self) -> spaces.MultiDiscrete:
        """Space of the subgoals this level receives (the action space of the level above)."""
        return subgoal_space(self.config.subgoal)

    def goal_features(self, subgoal: th.Tensor | None) -> th.Tensor | None:
        """What the actor sees of the received subgoal: the code, or its decoding (ablation 5.3.8); None at the top.

        :param subgoal: (N, n_cat * n_classes) one-hot code or None
        :return: (N, S') or None
        """
        if not self.subgoal_input:
            return None
        if subgoal is None:
            raise ValueError(f"level {self.level} takes a subgoal of shape (N, {self.subgoal_dim}), got None")
        if not self.decoded_subgoal_input:
            return subgoal
        with th.no_grad():
            return self.autoencoder.decode(subgoal)

    def features(
        self,
        window: th.Tensor,
        goal_feat: th.Tensor | None,
        reward: th.Tensor,
        cont: th.Tensor,
        prior_entropy: th.Tensor,
    ) -> th.Tensor:
        """Actor / critic input: the observed level-0 states, the subgoal and level 0's extras (eq. 4.6).

        :param window: (N, window, D + G*K) or (N, window * (D + G*K)) level-0 world states, oldest first
        :param goal_feat: (N, S') from :meth:`goal_features`, or None at the top
        :param reward: (N,) level 0's predicted reward at its current state
        :param cont: (N,) level 0's continue probability at its current state
        :param prior_entropy: (N,) entropy of level 0's prior at its current state
        :return: (N, feat_dim)
        """
        flat = window.reshape(window.shape[0], -1)
        if flat.shape[-1] != self.window * self.state_dim:
            raise ValueError(
                f"window has {flat.shape[-1]} features per row, expected window*state_dim = "
                f"{self.window}*{self.state_dim}"
            )
        z = flat[:, -self.stoch_dim :]  # the newest state's z; the split only orders the concatenation
        return actor_input(
            flat[:, : -self.stoch_dim],
            z,
            goal_feat,
            reward,
            cont,
            prior_entropy,
            use_extras=self.config.actor_critic.actor_extras,
        )

    @th.no_grad()
    def act(
        self,
        window: th.Tensor,
        reward: th.Tensor,
        cont: th.Tensor,
        prior_entropy: th.Tensor,
        subgoal: th.Tensor | None,
        deterministic: bool = False,
    ) -> th.Tensor:
        """Subgoal for the level below (no gradients).

        :param window: (N, window, D + G*K) observed level-0 states
        :param reward: (N,) level 0's predicted reward
        :param cont: (N,) level 0's continue probability
        :param prior_entropy: (N,) level 0's prior entropy
        :param subgoal: (N, n_cat * n_classes) subgoal from above, None at the top
        :param deterministic: the mode instead of a sample
        :return: (N, n_cat * n_classes) grouped one-hot
        """
        feat = self.features(window, self.goal_features(subgoal), reward, cont, prior_entropy)
        return self.actor_critic.act(feat, deterministic).reshape(window.shape[0], self.action_dim)

    @th.no_grad()
    def decode_subgoal(self, subgoal: th.Tensor) -> th.Tensor:
        """Received subgoal code -> target in level 0's h space.

        :param subgoal: (N, n_cat * n_classes) or (N, n_cat, n_classes)
        :return: (N, D)
        """
        return self.autoencoder.decode(subgoal)


def start_windows(features: th.Tensor, is_first: th.Tensor, size: int) -> th.Tensor:
    """The last ``size`` states up to every row of a chunk, zero where they lie before the chunk or the episode start.

    :param features: (B, T, F) world states of a chunk
    :param is_first: (B, T) episode starts
    :param size: window length (>= 1)
    :return: (B, T, size, F), oldest first; slot ``size - 1`` is row t itself
    """
    if features.dim() != 3 or tuple(is_first.shape) != tuple(features.shape[:2]):
        raise ValueError(
            f"features must be (B, T, F) and is_first (B, T), got {tuple(features.shape)} and {tuple(is_first.shape)}"
        )
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    pad = th.nn.functional.pad
    windows = pad(features, (0, 0, size - 1, 0)).unfold(1, size, 1).permute(0, 1, 3, 2)  # (B, T, size, F)
    episode = th.cumsum(is_first.long(), 1)  # (B, T): episode index within the chunk
    slots = pad(episode, (size - 1, 0), value=-1).unfold(1, size, 1)  # (B, T, size)
    valid = (slots == episode.unsqueeze(-1)).to(features.dtype)
    return windows * valid.unsqueeze(-1)


def train_shared_hierarchy(
    levels: Sequence[nn.Module], samples: SequenceSamples, config: HierosConfig
) -> list[dict[str, float]]:
    """One training iteration of every level of a shared-world-model hierarchy (ablation 5.3.1, module docstring).

    :param levels: level 0 (a :class:`Subactor`) and levels 1..L-1 (:class:`SharedLevel`)
    :param samples: a level-0 batch of chunks (B, T, ...); its ``subgoals`` are not used (imagined ones are)
    :param config: the hierarchy's configuration (``subgoal_interval``, ``imag_horizon``, ``higher_level_input``)
    :return: per level, its metrics (level 0 with the ``wm/*`` world-model metrics)
    """
    level0 = levels[0]
    if not isinstance(level0, Subactor) or not all(isinstance(lv, SharedLevel) for lv in levels[1:]):
        raise ValueError("levels must be a Subactor followed by SharedLevels (hierarchical_world_models=False)")
    n_levels, k, horizon = len(levels), config.subgoal_interval, config.imag_horizon
    if n_levels < 2 or horizon < k ** (n_levels - 1):
        raise ValueError(f"need >= 2 levels and imag_horizon >= k**(L-1), got L={n_levels}, H={horizon}, k={k}")
    wm = level0.world_model
    is_first = samples.is_first
    batch = SequenceSamples(
        samples.observations,
        level0.action_vectors(samples.actions, is_first),
        samples.rewards,
        is_first,
        samples.is_terminal,
        None,
    )
    # (1) world model of level 0
    metrics0, post = level0.world_model_step(batch, samples)

    # (2) joint imagination from every posterior state
    start = post.flatten_batch()
    n_all = int(start.batch_shape[0])
    first_cont = 1.0 - samples.is_terminal.reshape(n_all).float()  # (N,)
    with th.no_grad():
        chunk_states = wm.features(post)  # (B, T, D + G*K)
        windows = [None] + [
            start_windows(chunk_states, is_first, levels[i].window).reshape(n_all, levels[i].window, -1)
            for i in range(1, n_levels)
        ]
    chosen = imagination_start_indices(n_all, config.imag_start_fraction, first_cont.device)
    if chosen is not None:
        start, first_cont = start.select(chosen), first_cont[chosen]
        windows = [None] + [w[chosen] for w in windows[1:]]
    n = int(start.batch_shape[0])
    dynamics = level0.imag_gradient == "dynamics"
    extras = config.actor_critic.actor_extras
    with contextlib.nullcontext() if dynamics else th.no_grad(), wm.reuse_step_weights():
        state = start
        codes: list[th.Tensor | None] = [None] * n_levels  # codes[i]: subgoal in force for level i
        feats: list[list[th.Tensor]] = [[] for _ in range(n_levels)]
        acts: list[list[th.Tensor]] = [[] for _ in range(n_levels)]
        used: list[list[th.Tensor | None]] = [[] for _ in range(n_levels)]  # code in force at each decision
        states, rewards, conts = [start], [], []
        for t in range(horizon + 1):
            reward, cont, entropy = wm.reward(state), wm.cont(state), wm.prior_entropy(state)
            rewards.append(reward)
            conts.append(cont)
            for i in reversed(range(1, n_levels)):  # top-down, level i decides every k**i steps
                if t % k**i:
                    continue
                upper: Any = levels[i]
                feat = upper.features(windows[i], upper.goal_features(codes[i]), reward, cont, entropy)
                action = upper.actor_critic.actor(feat.detach()).sample()  # (N, G, K)
                feats[i].append(feat.detach())
                acts[i].append(action.detach())
                used[i].append(codes[i])
                codes[i - 1] = action.detach().reshape(n, -1)
            goal_feat = codes[0]
            if level0.decoded_subgoal_input:
                with th.no_grad():
                    goal_feat = level0.autoencoder.decode(codes[0])
            feat0 = actor_input(state.deter, state.stoch, goal_feat, reward, cont, entropy, use_extras=extras)
            feats[0].append(feat0)
            used[0].append(codes[0])
            if t == horizon:
                break
            action0 = level0.actor_critic.actor(feat0.detach()).sample()
            acts[0].append(action0)
            state, _ = wm.img_step(state, action0.reshape(n, level0.action_dim))
            states.append(state)
            newest = wm.features(state).detach().unsqueeze(1)
            for i in range(1, n_levels):
                windows[i] = th.cat([windows[i][:, 1:], newest], 1)
        traj = LatentState(*(th.stack(fields, 0) for fields in zip(*states, strict=True)))
        reward_all, cont_all = th.stack(rewards, 0), th.stack(conts, 0)  # (H+1, N)

        # (3) level 0: every imagined step; the subgoal reward of s_t against the subgoal a_{t-1} pursued
        targets = th.stack([level0.autoencoder.decode(c) for c in [used[0][0], *used[0][:-1]]], 0).detach()
        rewards0 = {"extrinsic": reward_all, "subgoal": max_cosine_subgoal_reward(traj.deter, targets)}
        if "novelty" in level0.reward_terms:
            with th.no_grad():
                rewards0["novelty"] = novelty_reward(traj.deter, level0.autoencoder)
    continues0 = th.cat([first_cont.unsqueeze(0), cont_all[1:].detach()], 0)
    tensors = learn_from_imagination(
        level0, th.stack(feats[0], 0), th.stack(acts[0], 0), rewards0, continues0, traj.deter
    )
    out = [metrics0]

    # (4) level i >= 1: every k**i-th imagined state
    reward_all, cont_all, deter = reward_all.detach(), cont_all.detach(), traj.deter.detach()
    for i in range(1, n_levels):
        level: Any = levels[i]
        stride = k**i
        steps = horizon // stride
        ext = th.zeros(steps + 1, n, device=deter.device)
        cont_i = th.ones(steps + 1, n, device=deter.device)
        cont_i[0] = first_cont
        for m in range(1, steps + 1):
            span = slice((m - 1) * stride + 1, m * stride + 1)
            ext[m] = reward_all[span].sum(0)
            cont_i[m] = cont_all[span].prod(0)
        h_i = deter[::stride][: steps + 1]  # (M+1, N, D)
        rewards_i = {"extrinsic": ext}
        with th.no_grad():
            if level.subgoal_input:
                goals = [used[i][0], *used[i][:steps]]  # s_m against the subgoal of decision m-1
                target = th.stack([level.autoencoder.decode(g) for g in goals], 0)
                rewards_i["subgoal"] = max_cosine_subgoal_reward(h_i, target)
            if "novelty" in level.reward_terms:
                rewards_i["novelty"] = novelty_reward(h_i, level.autoencoder)
        feats_i = th.stack(feats[i][: steps + 1], 0)
        acts_i = th.stack(acts[i][:steps], 0)
        out.append({"n_steps": float(steps)})
        out[i].update(metric_floats(learn_from_imagination(level, feats_i, acts_i, rewards_i, cont_i, deter)))
    out[0].update(metric_floats(tensors))
    return out
