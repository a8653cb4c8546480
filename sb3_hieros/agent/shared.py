"""Ablation 5.3.1: one world model for the whole hierarchy, i.e. HIEROS without hierarchical imagination.

With ``HierosConfig.hierarchical_world_models=False`` the hierarchy is a :class:`SharedWorldModelHierarchy`: only
level 0 is a full :class:`~sb3_hieros.agent.subactor.Subactor`, every level i >= 1 is a :class:`SharedLevel`, an
actor-critic and a subgoal autoencoder without a world model (thesis 5.3.1: "a hierarchy of subactors that uses only
one world model", Director-like):

* **Observation.** Level i observes the last ``k**i`` world states ``[h, z]`` of level 0's world model, concatenated
  (thesis 5.3.1: "k^i consecutive world model states"), or only the newest of them with
  ``higher_level_input="last"``. Its actor and critics also see the scalar extras of eq. 4.6 (reward, continue and
  prior entropy of level 0's current state) and, below the top, the subgoal from level i+1.
* **Subgoals.** All subgoals live in level 0's h space: the subgoal level i+1 gives to level i is decoded by level i's
  autoencoder, which is trained on level 0's h. Level i's subgoal reward is the max-cosine of level 0's h and that
  decoded subgoal; its novelty reward is its autoencoder's reconstruction error of level 0's h.
* **Training** (:meth:`SharedWorldModelHierarchy.train_step`, at every level-0 update; all levels train at every
  update). One world-model step of level 0 on the sampled chunk, then one *joint* imagination in level 0's world model
  from all B*T posterior states: at imagined step t every level i with ``t % k**i == 0`` acts (top-down) on its window
  of the last ``k**i`` level-0 states, so the subgoals change during imagination as they do when acting. The windows
  of the start states come from the chunk's posterior states (zero before the chunk's first row and before an episode
  start in the chunk, as when acting after a reset). Level i's trajectory is the imagined trajectory at every
  ``k**i``-th step, ``M = imag_horizon // k**i`` steps long: its extrinsic reward for step m is the sum of level 0's
  predicted rewards over the ``k**i`` imagined steps, its continue the product of their continue probabilities, and
  its subgoal and novelty rewards are taken at the arriving state.

Levels i >= 1 have no replay of their own and are not trained from replayed subgoals.
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any

import torch as th
from gymnasium import spaces
from torch import nn

from sb3_hieros.agent.actor_critic import actor_input, actor_input_dim
from sb3_hieros.agent.hierarchy import Encoded, Hierarchy, HierarchyState, Masks, _take
from sb3_hieros.agent.learning import LevelLearner, imagination_start_indices, learn_from_imagination
from sb3_hieros.agent.subactor import Subactor
from sb3_hieros.agent.subgoal import max_cosine_subgoal_reward, novelty_reward
from sb3_hieros.agent.world_model import LatentState
from sb3_hieros.config import HierosConfig
from sb3_hieros.nn.metrics import metric_floats
from sb3_hieros.nn.networks import check_bf16
from sb3_hieros.spaces import stacked_state_space, subgoal_space
from sb3_hieros.type_aliases import LevelUpdate, Observation, SequenceSamples

__all__ = ["SharedLevel", "SharedWorldModelHierarchy", "start_windows"]


class SharedLevel(LevelLearner):
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
    :param bf16: compute the actor-critic and autoencoder losses under a bfloat16 autocast: ``True``, ``False`` or
        ``"auto"`` (where the device computes bf16 natively)
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
        bf16: bool | str = False,
    ) -> None:
        super().__init__()
        sg = config.subgoal
        self.bf16 = check_bf16(bf16)
        self.config, self.level, self.window = config, level, window
        self.state_dim, self.h_dim, self.stoch_dim = state_dim, h_dim, stoch_dim
        self.subgoal_input = bool(subgoal_input)
        self.decoded_subgoal_input = bool(decoded_subgoal_input) and self.subgoal_input
        self.observation_space = stacked_state_space(state_dim, window)
        self.action_space = subgoal_space(sg)
        self.action_kind = "discrete"
        self.action_groups, self.action_classes = sg.n_cat, sg.n_classes
        self.action_dim = self.subgoal_dim = sg.n_cat * sg.n_classes
        self.imag_gradient = "reinforce"  # subgoals are categorical
        goal_feat = (h_dim if self.decoded_subgoal_input else self.subgoal_dim) if self.subgoal_input else 0
        extras = config.actor_critic.actor_extras
        self.feat_dim = actor_input_dim(window * state_dim - stoch_dim, stoch_dim, goal_feat, extras)
        self._build_learners(h_dim, self.feat_dim, "discrete", sg.n_classes, sg.n_cat, "reinforce")

    @property
    def optimizers(self) -> dict[str, th.optim.Optimizer]:
        """The three optimisers by name: ``actor``, ``critic``, ``autoencoder``."""
        return {"actor": self.actor_optimizer, "critic": self.critic_optimizer, "autoencoder": self.ae_optimizer}

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
    pad = th.nn.functional.pad
    windows = pad(features, (0, 0, size - 1, 0)).unfold(1, size, 1).permute(0, 1, 3, 2)  # (B, T, size, F)
    episode = th.cumsum(is_first.long(), 1)  # (B, T): episode index within the chunk
    slots = pad(episode, (size - 1, 0), value=-1).unfold(1, size, 1)  # (B, T, size)
    valid = (slots == episode.unsqueeze(-1)).to(features.dtype)
    return windows * valid.unsqueeze(-1)


class SharedWorldModelHierarchy(Hierarchy):
    """:class:`~sb3_hieros.agent.hierarchy.Hierarchy` with one world model (level 0's) for all levels (ablation
    5.3.1, module docstring). Only level 0 has a latent state and a replay; level i >= 1 keeps the last ``k**i``
    world states of level 0 and acts every ``k**i`` steps.

    :param observation_space: the environment's observation space
    :param action_space: the environment's action space
    :param config: the resolved configuration (``hierarchical_world_models=False``)
    :param world_model_options: ``bf16`` and ``compile`` opt-ins of the world model, its ``observation_options``
    """

    def _build_levels(
        self, observation_space: spaces.Space, action_space: spaces.Space, options: dict[str, Any]
    ) -> list[nn.Module]:
        level0 = Subactor(
            observation_space,
            action_space,
            self.config,
            level=0,
            subgoal_input=self.n_levels > 1,
            decoded_subgoal_input=self.config.decoded_subgoal_input,
            **options,
        )
        levels: list[nn.Module] = [level0]
        for i in range(1, self.n_levels):
            levels.append(
                SharedLevel(
                    level0.latent_dim,
                    level0.h_dim,
                    level0.z_dim,
                    1 if self.last_state_only else self.history_length(i),
                    self.config,
                    level=i,
                    subgoal_input=i < self.n_levels - 1,
                    decoded_subgoal_input=self.config.decoded_subgoal_input,
                    bf16=level0.bf16,
                )
            )
        return levels

    @property
    def replay_levels(self) -> int:
        """Only level 0 has a replay."""
        return 1

    def has_world_model(self, level: int) -> bool:
        """Only level 0 has a world model.

        :param level: index in ``[0, n_levels)``
        :return: ``level == 0``
        """
        return level == 0

    def history_length(self, level: int) -> int:
        """Level i keeps the last ``k**i`` world states of level 0.

        :param level: index in ``[1, n_levels)``
        :return: ``k**level``
        """
        return self.subgoal_interval**level

    def _history_dim(self, level: int) -> int:
        return self.levels[0].latent_dim

    def _encode(
        self, state: HierarchyState, observation: Observation, is_first: th.Tensor, masks: Masks, deterministic: bool
    ) -> Encoded:
        """Level 0 encodes o_t and every level i >= 1 pushes its world state into its window of the last ``k**i``.

        :return: level 0's latent state, the windows, and level 0's reward, continue and prior entropy (the actor
            extras of every level)
        """
        level0: Any = self.levels[0]
        latent = level0.observe_step(state.latents[0], observation, state.actions[0], is_first, deterministic)
        newest = level0.encoded_observation(latent).unsqueeze(1)  # (n, 1, D + G*K)
        keep = (~is_first).to(newest.dtype).reshape(state.n_envs, 1, 1)
        histories = tuple(th.cat([h[:, 1:] * keep, newest], 1) for h in state.histories)
        wm = level0.world_model
        return (latent,), histories, (wm.reward(latent), wm.cont(latent), wm.prior_entropy(latent))

    def _act(
        self, level: int, encoded: Encoded, index: th.Tensor | None, goal: th.Tensor | None, deterministic: bool
    ) -> th.Tensor:
        if level == 0:
            return super()._act(level, encoded, index, goal, deterministic)
        _, histories, extras = encoded
        window = _take(self.observation_window(histories[level - 1]), index)
        return self.levels[level].act(window, *(_take(x, index) for x in extras), goal, deterministic)

    def train_step(self, batches: Sequence[SequenceSamples | None]) -> list[LevelUpdate | None]:
        """One training iteration of every level in level 0's imagination (module docstring).

        :param batches: ``[batch]``, a level-0 batch of chunks (B, T, ...); its ``subgoals`` are not used (imagined
            ones are)
        :return: per level, its update (level 0 with the ``wm/*`` world-model metrics and the replay context)
        """
        (samples,) = batches
        assert samples is not None
        levels: Any = self.levels
        level0: Subactor = levels[0]
        n_levels, k, horizon = self.n_levels, self.subgoal_interval, self.config.imag_horizon
        wm = level0.world_model
        batch, _ = level0.training_batch(samples._replace(subgoals=None))
        is_first = batch.is_first
        # (1) world model of level 0
        tensors0, post, context = level0.world_model_step(batch, samples.context)
        lr = float(level0.wm_optimizer.param_groups[0]["lr"])

        # (2) joint imagination from every posterior state (or imag_start_fraction of them)
        start = post.flatten_batch()
        n_all = int(start.batch_shape[0])
        first_cont = 1.0 - batch.is_terminal.reshape(n_all).float()  # (N,)
        with th.no_grad():
            chunk_states = wm.features(post)  # (B, T, D + G*K)
            windows: list[Any] = [None] + [
                start_windows(chunk_states, is_first, levels[i].window).reshape(n_all, levels[i].window, -1)
                for i in range(1, n_levels)
            ]
        chosen = imagination_start_indices(n_all, self.config.imag_start_fraction, first_cont.device)
        if chosen is not None:
            start, first_cont = start.select(chosen), first_cont[chosen]
            windows = [None] + [w[chosen] for w in windows[1:]]
        n = int(start.batch_shape[0])
        dynamics = level0.imag_gradient == "dynamics"
        extras = self.config.actor_critic.actor_extras
        codes: list[th.Tensor | None] = [None] * n_levels  # codes[i]: subgoal in force for level i
        feats: list[list[th.Tensor]] = [[] for _ in range(n_levels)]
        acts: list[list[th.Tensor]] = [[] for _ in range(n_levels)]
        used: list[list[th.Tensor | None]] = [[] for _ in range(n_levels)]  # code in force at each decision
        rewards: list[th.Tensor] = []
        conts: list[th.Tensor] = []

        def step(t: int, state: LatentState) -> th.Tensor | None:
            if t > 0:  # the windows of level-0 states end with s_t
                newest = wm.features(state).detach().unsqueeze(1)
                for i in range(1, n_levels):
                    windows[i] = th.cat([windows[i][:, 1:], newest], 1)
            reward, cont, entropy = wm.reward(state), wm.cont(state), wm.prior_entropy(state)
            rewards.append(reward)
            conts.append(cont)
            for i in reversed(range(1, n_levels)):  # top-down, level i decides every k**i steps
                if t % k**i:
                    continue
                upper = levels[i]
                feat = upper.features(windows[i], upper.goal_features(codes[i]), reward, cont, entropy)
                action = upper.actor_critic.actor(feat.detach()).sample()  # (N, G, K)
                feats[i].append(feat.detach())
                acts[i].append(action.detach())
                used[i].append(codes[i])
                codes[i - 1] = action.detach().reshape(n, -1)
            goal_feat = level0.goal_features(codes[0])
            feat0 = actor_input(state.deter, state.stoch, goal_feat, reward, cont, entropy, use_extras=extras)
            feats[0].append(feat0)
            used[0].append(codes[0])
            if t == horizon:
                return None
            action0 = level0.actor_critic.actor(feat0.detach()).sample()
            acts[0].append(action0)
            return action0.reshape(n, level0.action_dim)

        with contextlib.nullcontext() if dynamics else th.no_grad():
            traj, _ = wm.rollout(start, horizon, step)
            reward_all, cont_all = th.stack(rewards, 0), th.stack(conts, 0)  # (H+1, N)

            # (3) level 0: every imagined step; the subgoal reward of s_t against the subgoal a_{t-1} pursued
            targets = th.stack([level0.autoencoder.decode(c) for c in [used[0][0], *used[0][:-1]]], 0).detach()
            rewards0 = {"extrinsic": reward_all, "subgoal": max_cosine_subgoal_reward(traj.deter, targets)}
            if "novelty" in level0.reward_terms:
                with th.no_grad():
                    rewards0["novelty"] = novelty_reward(traj.deter, level0.autoencoder)
        continues0 = th.cat([first_cont.unsqueeze(0), cont_all[1:].detach()], 0)
        tensors0.update(
            learn_from_imagination(
                level0, th.stack(feats[0], 0), th.stack(acts[0], 0), rewards0, continues0, traj.deter
            )
        )
        updates: list[LevelUpdate | None] = [LevelUpdate({**metric_floats(tensors0), "wm/lr": lr}, context)]

        # (4) level i >= 1: every k**i-th imagined state
        reward_all, cont_all, deter = reward_all.detach(), cont_all.detach(), traj.deter.detach()
        for i in range(1, n_levels):
            level = levels[i]
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
            learned = learn_from_imagination(level, feats_i, acts_i, rewards_i, cont_i, deter)
            updates.append(LevelUpdate({"n_steps": float(steps), **metric_floats(learned)}, None))
        return updates

    @th.no_grad()
    def decode_subgoals(self, state: HierarchyState) -> list[Observation]:
        """Every level's subgoal decoded into level 0's h space and turned into an observation by level 0's world
        model (with level 0's current z).

        :param state: the hierarchy state
        :return: per level i = 1 .. n_levels - 1, (n, *obs_shape) or a dict of such tensors
        """
        level0 = self.levels[0]
        return [
            level0.decode_state_observation(self.levels[i - 1].decode_subgoal(state.actions[i]), state.latents[0].stoch)
            for i in range(1, self.n_levels)
        ]
