"""HIEROS as a Stable-Baselines3 off-policy algorithm (thesis chapter 4; Algorithm 1 for acting, 2 for training).

:class:`HIEROS` reuses SB3's ``OffPolicyAlgorithm`` loop (``learn``, ``collect_rollouts``, callbacks, logging,
``save_replay_buffer``) and owns time: steps, the update schedule, the replay bookkeeping, logging and save/load. The
:class:`~sb3_hieros.policies.HierosPolicy` holds the :class:`~sb3_hieros.agent.hierarchy.Hierarchy`, which acts
(:meth:`~sb3_hieros.agent.hierarchy.Hierarchy.step`) and learns
(:meth:`~sb3_hieros.agent.hierarchy.Hierarchy.train_step`); the replays of the levels are described in
:mod:`sb3_hieros.buffers.levels`.

Hyperparameters: ``preset`` (``"paper"`` = thesis 4.6.3, ``"small"`` = CPU) gives every value, ``config_overrides``
(a dict for :meth:`HierosConfig.replace`, nested sections as dicts, e.g. ``{"world_model": {"s5_layers": 4}}``)
changes any field, and SB3's standard keywords ``learning_rate`` (the world models' learning rate, float or SB3
schedule, with the linear warm-up of ``world_model.warmup`` updates on top), ``buffer_size``, ``learning_starts``,
``batch_size``, ``gamma`` (``actor_critic.discount``) and ``policy_kwargs["net_arch"]`` (the actor's and critics'
sizes) win over both. The :class:`HierosConfig` is rebuilt from these in ``_setup_model`` (also on ``load``). SB3
keywords without a HIEROS meaning (``train_freq``, ``gradient_steps``, ``action_noise``, ...) raise a ``ValueError``
that says what HIEROS uses instead.

Training schedule: ``train_ratio`` is DreamerV3's replayed steps per environment step: level 0 makes
``train_ratio * n_envs / (batch_size * batch_length)`` updates per vec-env step (the fraction is carried over), and
level i >= 1 trains at every ``k**i``-th level-0 update once its buffer can sample; each of these updates is preceded
by ``world_model_updates - 1`` world-model updates of the level on batches of their own. No update happens before
``learning_starts`` steps (uniformly random actions at every level until then, while the hierarchy still encodes every
observation) or while level 0's buffer cannot sample a chunk (e.g. right after ``load``). With
``actor_learning_starts`` above ``learning_starts``, the updates in between train the world models alone (each of
them ``world_model_updates`` times) and every level goes on acting at random until ``actor_learning_starts``.

Logging: SB3's ``rollout/*``, ``time/*``, ``train/learning_rate``, ``train/n_updates``, and
``train/level{i}/<metric>`` for every metric of :meth:`Subactor.train_step` (mean over the updates since the last
dump) plus ``train/level{i}/n_updates`` and ``train/level{i}/skipped_updates``.

Faults (``docs/resume.md``): non-finite observations and rewards raise ``ValueError`` before they reach the replay;
an optimiser step with a non-finite loss or gradient norm is skipped, and ``max_nonfinite_updates`` such updates of
one level in a row raise ``FloatingPointError``; saves are written atomically and checked on loading
(:mod:`sb3_hieros.save_util`, ``load(..., safe=True)`` unpickles nothing).
"""

from __future__ import annotations

import dataclasses
import io
import pathlib
import pickle
import warnings
import zipfile
import zlib
from collections.abc import Iterable
from typing import Any, ClassVar, TypeVar

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.policies import BasePolicy
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule

from sb3_hieros.agent.hierarchy import HierarchyState
from sb3_hieros.agent.world_model import set_world_model_lr
from sb3_hieros.buffers import DictSequenceReplayBuffer, ETBSReplayBuffer, SequenceReplayBuffer
from sb3_hieros.buffers.levels import HigherLevelRows, SubgoalTransitions, make_level_buffers
from sb3_hieros.config import HierosConfig, config_from_dict, get_preset
from sb3_hieros.keywords import CONFIG_ONLY, actor_critic_sizes, refuse_keywords
from sb3_hieros.nn.guard import count_nonfinite, nonfinite_error
from sb3_hieros.policies import CnnPolicy, HierosPolicy, MlpPolicy, MultiInputPolicy
from sb3_hieros.replay_io import read_replay, write_replay
from sb3_hieros.save_util import prepare_model_load, qualified_name, safe_load_values, write_archive
from sb3_hieros.spaces import check_finite_observations, check_finite_step
from sb3_hieros.type_aliases import LevelUpdate, Observation, SequenceSamples

__all__ = ["HIEROS"]

SelfHIEROS = TypeVar("SelfHIEROS", bound="HIEROS")

#: the defaults that have changed since models are saved with their configuration: older saves were trained with these
DEFAULTS_BEFORE_SAVED_CONFIG: dict[str, Any] = {
    "actor_critic": {"return_normalization": "per_term"},
    "world_model": {"deter_from": "state"},
    "world_model_updates": 1,
}


class HIEROS(OffPolicyAlgorithm):
    """HIEROS: hierarchical imagination on S5 world models with efficient time-balanced replay (Mattes 2023).

    :param policy: ``"MlpPolicy"``, ``"CnnPolicy"``, ``"MultiInputPolicy"`` or a :class:`HierosPolicy` subclass
    :param env: environment (gymnasium env, VecEnv or registered id)
    :param preset: ``"paper"`` (thesis 4.6.3, for a GPU; built on a CPU it warns) or ``"small"`` (CPU); fills every
        value not given
    :param learning_rate: world-model learning rate of every level (float or schedule); None = preset
    :param buffer_size: level-0 replay capacity in steps (level i: ``buffer_size // k**i``); None = preset
    :param learning_starts: environment steps of uniformly random actions before training; None = preset
    :param batch_size: chunks per update; None = preset
    :param gamma: discount of every level's returns (``actor_critic.discount``); None = preset
    :param replay_buffer_class: level-0 buffer class, a :class:`SequenceReplayBuffer` subclass; None =
        :class:`ETBSReplayBuffer`
    :param replay_buffer_kwargs: extra keywords of the level-0 buffer
    :param config_overrides: changes to the preset (:meth:`HierosConfig.replace` keywords; nested sections as dicts),
        e.g. ``{"n_levels": 2, "train_ratio": 64.0, "world_model": {"kind": "rssm"}}``
    :param max_nonfinite_updates: training stops with ``FloatingPointError`` when this many updates in a row of one
        level had a non-finite loss or gradient (each such optimiser step is skipped, see the module docstring)
    :param policy_kwargs: keywords of the policy: ``bf16``, ``compile`` and SB3's ``normalize_images``,
        ``optimizer_class`` / ``optimizer_kwargs`` (every optimiser of every level), ``features_extractor_class`` /
        ``features_extractor_kwargs`` (level 0's encoder); ``net_arch`` sets the actor and critic sizes
        (:func:`~sb3_hieros.keywords.actor_critic_sizes`); see :class:`HierosPolicy`
    :param stats_window_size: window of the rollout statistics
    :param tensorboard_log: tensorboard log directory
    :param verbose: 0 silent, 1 info, 2 debug
    :param seed: random seed
    :param device: torch device
    :param _init_setup_model: build the networks and buffers now
    :param kwargs: none; hyperparameters such as ``n_levels`` are set with ``config_overrides``, and keywords of SB3's
        other algorithms without a HIEROS meaning (``train_freq``, ``gradient_steps``, ``action_noise``, ``tau``,
        ...) are refused; a ``ValueError`` says what HIEROS uses instead
    """

    policy_aliases: ClassVar[dict[str, type[BasePolicy]]] = {
        "MlpPolicy": MlpPolicy,
        "CnnPolicy": CnnPolicy,
        "MultiInputPolicy": MultiInputPolicy,
    }
    policy: HierosPolicy
    replay_buffer: SequenceReplayBuffer  # type: ignore[assignment]

    def __init__(
        self,
        policy: str | type[HierosPolicy],
        env: GymEnv | str | None,
        preset: str = "paper",
        learning_rate: float | Schedule | None = None,
        buffer_size: int | None = None,
        learning_starts: int | None = None,
        batch_size: int | None = None,
        gamma: float | None = None,
        replay_buffer_class: type[SequenceReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        config_overrides: dict[str, Any] | None = None,
        max_nonfinite_updates: int = 10,
        policy_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
        **kwargs: Any,
    ) -> None:
        refuse_keywords(kwargs)
        if config_overrides is not None and not isinstance(config_overrides, dict):
            raise ValueError(f"config_overrides must be a dict or None, got {type(config_overrides).__name__}")
        for name in ("config", "images_channel_first"):
            if policy_kwargs is not None and name in policy_kwargs:
                raise ValueError(
                    f"policy_kwargs must not contain {name!r}: HIEROS builds the policy's config from preset, "
                    "config_overrides and SB3's keywords, and wraps image envs by SB3's rule; put configuration "
                    "changes into config_overrides"
                )
        if policy_kwargs is not None and "net_arch" in policy_kwargs:
            actor_critic_sizes(policy_kwargs["net_arch"])
        integer = isinstance(max_nonfinite_updates, int | np.integer) and not isinstance(max_nonfinite_updates, bool)
        if not integer or max_nonfinite_updates < 1:
            raise ValueError(f"max_nonfinite_updates must be an int >= 1, got {max_nonfinite_updates!r}")
        base = get_preset(preset).replace(**(config_overrides or {}))
        given = {"buffer_size": buffer_size, "learning_starts": learning_starts, "batch_size": batch_size}
        keywords = {name: getattr(base, name) if value is None else value for name, value in given.items()}
        super().__init__(
            policy,
            env,
            learning_rate=base.world_model.lr if learning_rate is None else learning_rate,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=False,
            policy_kwargs=policy_kwargs,
            gamma=base.actor_critic.discount if gamma is None else gamma,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            train_freq=(1, "step"),
            support_multi_env=True,
            seed=seed,
            use_sde=False,
            sde_support=False,
            gradient_steps=-1,
            supported_action_spaces=(spaces.Discrete, spaces.Box),
            **keywords,
        )
        self.preset = preset
        self.config_overrides = dict(config_overrides or {})
        self.max_nonfinite_updates = int(max_nonfinite_updates)
        self.config: HierosConfig | None = None
        # training-time state of the hierarchy and of its replay rows (built in _setup_learn, never saved)
        self._hier: HierarchyState | None = None
        self._rows: HigherLevelRows | None = None
        self._subgoal0: np.ndarray | None = None
        # update schedule (saved)
        self._update_budget = 0.0
        # the resolved configuration as plain values, saved with the model so that it loads as it was trained
        self._config_fields: dict[str, Any] | None = None
        self._level_updates: list[int] | None = None
        # non-finite guard, per level: updates with a skipped optimiser step (total and current run of them)
        self._skipped_updates: list[int] | None = None
        self._nonfinite_streak: list[int] | None = None
        if _init_setup_model:
            self._setup_model()
            if self.preset == "paper" and self.device.type == "cpu":
                n_params = sum(p.numel() for p in self.policy.parameters())
                warnings.warn(
                    f"HIEROS builds the 'paper' preset (thesis 4.6.3, {n_params / 1e6:.1f}M parameters for this env; "
                    "it is the default when preset is not given) on a CPU, where training it is very slow. On a CPU "
                    'pass preset="small"; the paper preset is meant for a CUDA GPU (device="auto" picks one).',
                    UserWarning,
                    stacklevel=2,
                )

    # ------------------------------------------------------------------------------------------------ setup

    def _build_config(self) -> HierosConfig:
        """The configuration from preset, ``config_overrides`` and SB3's keywords (see the module docstring). A loaded
        model starts from the configuration it was saved with instead of the preset, so that a later change of a
        preset's values does not change it."""
        saved = self._config_fields
        base = config_from_dict(saved) if saved is not None else get_preset(self.preset)
        config = base.replace(**self.config_overrides)
        # saves of models built when these were constructor keywords hold them as attributes
        legacy = {name: self.__dict__[name] for name in CONFIG_ONLY if name in self.__dict__}
        keywords = {name: getattr(self, name) for name in ("buffer_size", "learning_starts", "batch_size")}
        actor_critic: dict[str, Any] = {"discount": float(self.gamma)}
        if "net_arch" in self.policy_kwargs:
            actor_critic.update(actor_critic_sizes(self.policy_kwargs["net_arch"]))
        return config.replace(
            **legacy, **keywords, world_model={"lr": float(self.lr_schedule(1.0))}, actor_critic=actor_critic
        )

    def _setup_model(self) -> None:
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        self.config = self._build_config()
        self._config_fields = dataclasses.asdict(self.config)
        self.gamma = self.config.actor_critic.discount
        self._convert_train_freq()
        policy_kwargs = {name: value for name, value in self.policy_kwargs.items() if name != "net_arch"}
        self.policy = self.policy_class(
            self.observation_space,
            self.action_space,
            self.lr_schedule,
            config=self.config,
            images_channel_first=True,  # the env was wrapped by SB3's rule (VecTransposeImage, or the user's)
            **policy_kwargs,
        ).to(self.device)
        if self.replay_buffer is None:
            self.replay_buffer = self._make_replay_buffers()
        for name in ("_level_updates", "_skipped_updates", "_nonfinite_streak"):
            if getattr(self, name, None) is None or len(getattr(self, name)) != self.config.n_levels:
                setattr(self, name, [0] * self.config.n_levels)
        self._hier = None
        self._rows = None
        self._subgoal0 = None

    def _make_replay_buffers(self) -> SequenceReplayBuffer:
        """One replay per level with a world model (:func:`~sb3_hieros.buffers.levels.make_level_buffers`)."""
        assert self.config is not None
        hierarchy = self.policy.hierarchy
        levels = hierarchy.levels[: hierarchy.replay_levels]
        level_spaces = [(self.observation_space, self.action_space)]
        level_spaces += [(level.observation_space, level.action_space) for level in levels[1:]]
        contexts = [level.world_model.context_dim if self.config.replay_context else 0 for level in levels]
        return make_level_buffers(
            self.config,
            level_spaces,
            contexts,
            self.buffer_size,
            self.n_envs,
            self.device,
            self.replay_buffer_class,
            self.replay_buffer_kwargs,
        )

    def level_buffers(self) -> list[SequenceReplayBuffer]:
        """The replay buffer of every level, level 0 (``self.replay_buffer``) first.

        :return: list of buffers
        """
        return [self.replay_buffer, *getattr(self.replay_buffer, "higher_levels", [])]

    def save_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase) -> None:
        """Save the replay of every level without pickle (:mod:`sb3_hieros.replay_io`), atomically: a crash during the
        save leaves the previous file at ``path`` intact (:mod:`sb3_hieros.save_util`).

        :param path: file (``.pkl`` appended when it has no suffix, as in SB3; the content is a zip) or binary file
        """
        buffers = self.level_buffers()
        write_archive(path, lambda target: write_replay(target, buffers), suffix="pkl")

    def load_replay_buffer(self, path: str | pathlib.Path | io.BufferedIOBase, truncate_last_traj: bool = True) -> None:
        """Load the replay of every level, written by :meth:`save_replay_buffer` (or a legacy pickle, with a warning).

        The file is checked against this model's buffers (levels, ``n_envs``, rows, every array's dtype and shape,
        checksums) before anything is replaced; on ``ValueError`` the model's replay is unchanged. The loaded buffers
        sample onto the model's current device.

        :param path: the file or a binary file object
        :param truncate_last_traj: unused (SB3's HER option)
        """
        # after ``model.replay_buffer = None`` (as SB3's tests do) fresh buffers describe what the file must hold
        if self.replay_buffer is None:
            self.replay_buffer = self._make_replay_buffers()
        buffers = read_replay(path, self.level_buffers())
        for buffer in buffers:  # the model's current device, as SB3 does
            buffer.device = self.device
        self.replay_buffer = buffers[0]

    def _setup_learn(
        self,
        total_timesteps: int,
        callback: MaybeCallback = None,
        reset_num_timesteps: bool = True,
        tb_log_name: str = "run",
        progress_bar: bool = False,
    ) -> tuple[int, Any]:
        fresh = reset_num_timesteps or self._last_obs is None or self._hier is None
        fresh = fresh or (self._hier is not None and self._hier.n_envs != self.n_envs)
        result = super()._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        # the observations of later steps are checked as they arrive (_store_transition)
        check_finite_observations(self._last_obs, "reset observation")  # type: ignore[arg-type]
        if fresh:
            self._reset_hierarchy()
        return result

    def _reset_hierarchy(self) -> None:
        """Fresh training-time hierarchy state for ``n_envs`` envs; every env starts an episode at its next step."""
        assert self.config is not None
        self._hier = self.policy.hierarchy.initial_state(self.n_envs)
        zero = self.config.reference.terminal_reward == "zeroed"
        self._rows = HigherLevelRows(self.policy.hierarchy.replay_levels, self.n_envs, zero)
        self._subgoal0 = None
        self._last_episode_starts = np.ones(self.n_envs, dtype=bool)

    # ------------------------------------------------------------------------------------------------ acting

    def _sample_action(
        self, learning_starts: int, action_noise: Any = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """One step of the hierarchy on ``self._last_obs`` (Algorithm 1) with exploration, and the rows of the levels
        above 0 that updated.

        Before ``learning_starts`` (or ``actor_learning_starts``, the later of the two) every level takes uniformly
        random actions, but every observation is still encoded so that the latent states and histories stay
        consistent. Afterwards the actors sample.

        :param learning_starts: steps of random warm-up
        :param action_noise: unsupported (must be None)
        :param n_envs: number of envs
        :return: environment action and buffer action (Box: scaled to [-1, 1]; Discrete: indices)
        """
        if action_noise is not None:
            raise ValueError("HIEROS explores with its stochastic actors; action_noise must be None")
        assert self._hier is not None and self._rows is not None and self.config is not None
        policy, hierarchy = self.policy, self.policy.hierarchy
        obs, _ = policy.obs_to_tensor(self._last_obs)  # type: ignore[arg-type]
        is_first = np.asarray(self._last_episode_starts, dtype=bool)
        acting = max(learning_starts, self.actors_start)  # actors_start itself when SB3 passes self.learning_starts
        random_actions = policy.random_action_vectors(n_envs) if self.num_timesteps < acting else None
        self._hier, step = hierarchy.step(self._hier, obs, th.as_tensor(is_first), False, random_actions)
        buffers = self.level_buffers()
        for rows in hierarchy.update_rows(self._hier, step):
            self._rows.write(buffers[rows.level], rows, is_first[rows.envs], False)
        self._subgoal0 = self._hier.actions[1].cpu().numpy() if len(self._hier.actions) > 1 else None
        vector = self._hier.actions[0]
        action = policy.env_actions(vector)
        if isinstance(self.action_space, spaces.Box):
            return action, vector.float().cpu().numpy()
        return action, action

    @th.no_grad()
    def _write_terminal_rows(self, dones: np.ndarray, infos: list[dict[str, Any]]) -> None:
        """At episode ends: encode the terminal observation bottom-up and write every level's terminal row."""
        assert self._hier is not None and self._rows is not None
        envs = np.flatnonzero(dones)
        terminated = np.array([not infos[j].get("TimeLimit.truncated", False) for j in envs], dtype=bool)
        final = [infos[j].get("terminal_observation") for j in envs]
        obs = None
        if all(o is not None for o in final):
            if isinstance(final[0], dict):
                stacked: Any = {key: np.stack([o[key] for o in final]) for key in final[0]}
            else:
                stacked = np.stack(final)
            obs, _ = self.policy.obs_to_tensor(stacked)
        buffers = self.level_buffers()
        for rows in self.policy.hierarchy.encode_terminal(self._hier, obs, envs):
            self._rows.write(buffers[rows.level], rows, False, terminated)

    def _store_transition(
        self,
        replay_buffer: ReplayBuffer,
        buffer_action: np.ndarray,
        new_obs: np.ndarray | dict[str, np.ndarray],
        reward: np.ndarray,
        dones: np.ndarray,
        infos: list[dict[str, Any]],
    ) -> None:
        """Level 0 through SB3 (with the subgoal in force), then the higher levels' reward sums and terminal rows."""
        check_finite_step(new_obs, reward, dones, infos)
        zero_terminal_reward = self.config is not None and self.config.reference.terminal_reward == "zeroed"
        target: Any = replay_buffer
        if self._subgoal0 is not None or zero_terminal_reward:
            target = SubgoalTransitions(replay_buffer, self._subgoal0, zero_terminal_reward)  # type: ignore[arg-type]
        super()._store_transition(target, buffer_action, new_obs, reward, dones, infos)
        assert self._rows is not None
        done = np.asarray(dones, dtype=bool).reshape(-1)
        self._rows.add_rewards(reward, done)
        if done.any() and self.policy.hierarchy.replay_levels > 1:
            self._write_terminal_rows(done, infos)
        self._last_episode_starts = done.copy()

    # ------------------------------------------------------------------------------------------------ training

    def _record_level(self, level: int, metrics: dict[str, float], count: bool = True) -> None:
        """Log one update of ``level`` (counted in its updates if ``count``) and count its skipped (non-finite)
        optimiser steps (:func:`~sb3_hieros.nn.guard.count_nonfinite`)."""
        assert self._level_updates is not None
        self._level_updates[level] += int(count)
        for key, value in metrics.items():
            self.logger.record_mean(f"train/level{level}/{key}", value)
        assert self._skipped_updates is not None and self._nonfinite_streak is not None
        skipped = count_nonfinite(metrics, level, self._skipped_updates, self._nonfinite_streak)
        if skipped:
            self.logger.record(f"train/level{level}/skipped_updates", self._skipped_updates[level])
            in_a_row = self._nonfinite_streak[level]
            if in_a_row >= self.max_nonfinite_updates:
                raise nonfinite_error(metrics, level, skipped, in_a_row, self.max_nonfinite_updates)

    def _sample_batches(self, levels: list[int], batch_size: int, lr: float) -> list[SequenceSamples | None]:
        """A batch of each of ``levels``' replays (None for the others), their world models' learning rates set.

        :param levels: the levels that train now
        :param batch_size: chunks per batch
        :param lr: the value of the learning-rate schedule
        :return: per level with a replay, its batch or None
        """
        assert self._level_updates is not None
        buffers, hierarchy = self.level_buffers(), self.policy.hierarchy
        batches: list[SequenceSamples | None] = [None] * len(buffers)
        for i in levels:
            level = hierarchy.levels[i]
            set_world_model_lr(level.wm_optimizer, level.wm_scheduler, lr, self._level_updates[i])
            batches[i] = buffers[i].sample(batch_size, env=self._vec_normalize_env if i == 0 else None)
        return batches

    def _apply_updates(
        self, batches: list[SequenceSamples | None], updates: list[LevelUpdate | None], count: bool
    ) -> None:
        """Log the levels' updates and store their replay contexts.

        :param batches: per level with a replay, the batch it trained on or None
        :param updates: per level, what its update returned or None
        :param count: whether these are the levels' updates of the schedule (False for the extra world-model updates
            of ``world_model_updates``, which are logged but not counted)
        """
        buffers = self.level_buffers()
        for i, update in enumerate(updates):
            if update is None:
                continue
            self._record_level(i, update.metrics, count)
            batch = batches[i] if i < len(batches) else None
            if update.context is not None and batch is not None and batch.index is not None:
                buffers[i].store_context(batch.index, update.context)

    def train(self, gradient_steps: int, batch_size: int) -> None:
        """Level updates for ``gradient_steps`` new environment steps (see the module docstring's schedule).

        :param gradient_steps: environment steps collected since the last call (SB3 passes ``n_envs`` per vec step)
        :param batch_size: chunks per update
        """
        assert self.config is not None and self._level_updates is not None
        buffers = self.level_buffers()
        if not buffers[0].can_sample():
            return
        cfg = self.config
        self._update_budget += gradient_steps * cfg.train_ratio / (cfg.batch_size * cfg.batch_length)
        n_updates = int(self._update_budget)
        self._update_budget -= n_updates
        if n_updates == 0:
            return
        self.policy.set_training_mode(True)
        lr = float(self.lr_schedule(self._current_progress_remaining))
        self.logger.record("train/learning_rate", lr)
        hierarchy = self.policy.hierarchy
        for _ in range(n_updates):
            due = [i for i in hierarchy.levels_due(self._level_updates[0]) if buffers[i].can_sample()]
            for _ in range(cfg.world_model_updates - 1):
                batches = self._sample_batches(due, batch_size, lr)
                self._apply_updates(batches, hierarchy.world_model_updates(batches), count=False)
            batches = self._sample_batches(due, batch_size, lr)
            if self.num_timesteps < self.actors_start:  # the world models alone until the actors start
                self._apply_updates(batches, hierarchy.world_model_updates(batches), count=True)
            else:
                self._apply_updates(batches, hierarchy.train_step(batches), count=True)
            self._n_updates += 1
        self.policy.set_training_mode(False)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for i, count in enumerate(self._level_updates):
            self.logger.record(f"train/level{i}/n_updates", count, exclude="tensorboard")
        for i, count in enumerate(self._skipped_updates or []):
            self.logger.record(f"train/level{i}/skipped_updates", count)

    def learn(
        self: SelfHIEROS,
        total_timesteps: int,
        callback: MaybeCallback = None,
        log_interval: int = 4,
        tb_log_name: str = "HIEROS",
        reset_num_timesteps: bool = True,
        progress_bar: bool = False,
    ) -> SelfHIEROS:
        """Train for ``total_timesteps`` environment steps (SB3's ``learn``; default ``tb_log_name="HIEROS"``).

        :param total_timesteps: environment steps (a lower bound: the loop finishes its vec-env step); a
            ``UserWarning`` says when the run ends before ``learning_starts`` is passed, i.e. before the first update
        :param callback: SB3 callback(s)
        :param log_interval: dump the logs every ``log_interval`` episodes
        :param tb_log_name: tensorboard run name
        :param reset_num_timesteps: restart the step counter (and the envs and the hierarchy)
        :param progress_bar: show a progress bar (tqdm and rich)
        :return: self
        """
        steps_at_end = total_timesteps + (0 if reset_num_timesteps else self.num_timesteps)
        if steps_at_end <= self.learning_starts:
            warnings.warn(
                f"learn({total_timesteps}) ends at {steps_at_end} environment steps, before the first update: HIEROS "
                f"acts at random and does not train during the first learning_starts={self.learning_starts} steps. "
                f"Train for more than {self.learning_starts - (steps_at_end - total_timesteps)} steps or lower "
                "learning_starts.",
                UserWarning,
                stacklevel=2,
            )
        return super().learn(
            total_timesteps=total_timesteps,
            callback=callback,
            log_interval=log_interval,
            tb_log_name=tb_log_name,
            reset_num_timesteps=reset_num_timesteps,
            progress_bar=progress_bar,
        )

    # ------------------------------------------------------------------------------------------------ saving

    @classmethod
    def load(  # type: ignore[override]
        cls: type[SelfHIEROS],
        path: str | pathlib.Path | io.BufferedIOBase,
        env: GymEnv | None = None,
        device: th.device | str = "auto",
        custom_objects: dict[str, Any] | None = None,
        print_system_info: bool = False,
        force_reset: bool = True,
        safe: bool = False,
        **kwargs: Any,
    ) -> SelfHIEROS:
        """SB3's ``load``, refusing files that are not an intact HIEROS save with a short ``ValueError``.

        A truncated or corrupted zip, a member that does not match the checksum recorded at saving, a zip without
        HIEROS's data, or a save of another algorithm (e.g. DQN) raise ``ValueError`` before anything is built; a
        corrupted tensor file inside the zip raises ``ValueError`` with torch's message instead of torch's traceback.
        An env whose spaces differ from the saved ones raises ``ValueError``.

        SB3 keeps spaces, classes and schedules as pickles in the zip, and unpickling runs whatever code the file
        names: load files you did not save yourself with ``safe=True``, which unpickles nothing (spaces from ``env``,
        the policy class, learning rate and episode statistics from plain values of the file; the env is reset
        before training goes on). Without it every pickled entry is unpickled once.

        :param path: zip file (``.zip`` may be omitted) or file-like object
        :param env: environment to attach (spaces must match the saved ones), or None
        :param device: torch device
        :param custom_objects: values replacing saved attributes (see SB3)
        :param print_system_info: print the system info of the save
        :param force_reset: reset the env before training continues (SB3: avoids unexpected behaviour)
        :param safe: load without unpickling anything (``env`` required); for files from elsewhere
        :param kwargs: attributes to set on the loaded model (e.g. ``learning_starts=0``)
        :return: the model
        """
        env_spaces = None
        if safe:
            if env is None:
                raise ValueError("HIEROS.load(..., safe=True) takes the spaces from the env: pass env=...")
            env = cls._wrap_env(env, verbose=0)
            env_spaces = (env.observation_space, env.action_space)
        custom_objects, data = prepare_model_load(
            path,
            custom_objects,
            safe,
            env_spaces,
            HierosPolicy,
            {qualified_name(p): p for p in cls.policy_aliases.values()},  # type: ignore[misc]
            {qualified_name(b): b for b in (SequenceReplayBuffer, DictSequenceReplayBuffer, ETBSReplayBuffer)},  # type: ignore[misc]
        )
        if "_config_fields" not in data and "_config_fields" not in kwargs:
            # saved before the configuration was: rebuild it as it was then
            preset = kwargs.get("preset", data.get("preset", "paper"))
            legacy = get_preset(preset).replace(**DEFAULTS_BEFORE_SAVED_CONFIG)
            kwargs["_config_fields"] = dataclasses.asdict(legacy)
        try:
            return super().load(  # type: ignore[return-value]
                path,
                env=env,
                device=device,
                custom_objects=custom_objects,
                print_system_info=print_system_info,
                force_reset=force_reset,
                **kwargs,
            )
        except (RuntimeError, EOFError, zipfile.BadZipFile, zlib.error, pickle.UnpicklingError) as err:
            raise ValueError(
                f"{path} could not be loaded as a HIEROS model (corrupted file?): {type(err).__name__}: {err}"
            ) from None

    def set_parameters(
        self,
        load_path_or_dict: str | pathlib.Path | io.BufferedIOBase | dict[str, Any],
        exact_match: bool = True,
        device: th.device | str = "auto",
    ) -> None:
        """SB3's ``set_parameters``; the optimiser entries of saves whose policy held the levels directly
        (``policy.levels.*``) are read as those of ``policy.hierarchy.levels.*``.

        :param load_path_or_dict: a zip file or the dict of state dicts of :meth:`get_parameters`
        :param exact_match: all parameters and optimisers must be given
        :param device: torch device of the loaded tensors
        """
        params = load_path_or_dict
        if not isinstance(params, dict):
            _, params, _ = load_from_zip_file(params, device=device)
        old = "policy.levels."
        renamed = {
            ("policy.hierarchy.levels." + k[len(old) :] if k.startswith(old) else k): v for k, v in params.items()
        }
        super().set_parameters(renamed, exact_match=exact_match, device=device)

    def save(
        self,
        path: str | pathlib.Path | io.BufferedIOBase,
        exclude: Iterable[str] | None = None,
        include: Iterable[str] | None = None,
    ) -> None:
        """SB3's ``save``, written atomically (a crash during the save leaves the previous file at ``path`` intact)
        with the checksum of every member and the plain values ``load(..., safe=True)`` needs
        (:mod:`sb3_hieros.save_util`).

        :param path: zip file (``.zip`` appended when it has no suffix) or binary file object
        :param exclude: attributes not to save, besides the default ones
        :param include: attributes to save although excluded by default
        """
        write_archive(
            path, lambda target: super(HIEROS, self).save(target, exclude, include), "zip", safe_load_values(self)
        )

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "config", "_hier", "_rows", "_subgoal0"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", *(f"policy.{name}" for name in self.policy.optimizer_names())], []

    # ------------------------------------------------------------------------------------------------ inspection

    def level_updates(self) -> list[int]:
        """Updates each level has made so far, level 0 first (``train/level{i}/n_updates``).

        :return: one count per level
        """
        return list(self._level_updates or [])

    def skipped_updates(self) -> list[int]:
        """Updates of each level with a skipped (non-finite) optimiser step so far (``train/level{i}/skipped_updates``).

        :return: one count per level
        """
        return list(self._skipped_updates or [])

    @property
    def actors_start(self) -> int:
        """The environment step from which the actors choose the actions and learn: the later of ``learning_starts``
        and the config's ``actor_learning_starts``. Every level acts uniformly at random before it."""
        assert self.config is not None
        return max(self.learning_starts, self.config.actor_learning_starts)

    @property
    def update_budget(self) -> float:
        """The fraction of a level-0 update carried over to the next :meth:`train` call (the ``train_ratio``
        schedule): a vec-env step adds ``train_ratio * n_envs / (batch_size * batch_length)``, and every whole update
        in it is made."""
        return self._update_budget

    @property
    def hierarchy_state(self) -> HierarchyState | None:
        """The hierarchy's recurrent state during ``learn`` (after the last step), None before the first ``learn``."""
        return self._hier

    def decoded_subgoals(self) -> tuple[np.ndarray | dict[str, np.ndarray], list[Observation]] | None:
        """The observation the hierarchy encoded last during ``learn`` (as the model sees it, normalised under
        VecNormalize) and, for it, the subgoal in force from every level i >= 1 decoded into the observation space
        (:meth:`~sb3_hieros.agent.hierarchy.Hierarchy.decode_subgoals`, thesis 4.3.2).

        :return: (observations (n_envs, ...), per level i >= 1 the decoded observations), or None before ``learn``
        """
        if self._hier is None or self._last_obs is None:
            return None
        return self._last_obs, self.policy.hierarchy.decode_subgoals(self._hier)
