"""HIEROS as a Stable-Baselines3 off-policy algorithm (thesis chapter 4; Algorithm 1 for acting, 2 for training).

:class:`HIEROS` reuses SB3's ``OffPolicyAlgorithm`` loop (``learn``, ``collect_rollouts``, callbacks, logging,
``save_replay_buffer``); it owns time (steps, update schedule, replay bookkeeping, logging), the
:class:`~sb3_hieros.policies.HierosPolicy` owns the levels and acting, each
:class:`~sb3_hieros.agent.subactor.Subactor` owns its learning.

Hyperparameters
---------------
``preset`` (``"paper"`` = thesis 4.6.3, ``"small"`` = CPU) gives every value; ``config_overrides`` (a dict for
:meth:`HierosConfig.replace`, nested sections as dicts, e.g. ``{"world_model": {"s5_layers": 4}}``) changes any
field; the explicit constructor keywords (``learning_rate``, ``buffer_size``, ...) win over both. Explicit keywords
left at None take the value from preset + overrides, and the resolved value is stored as the attribute of the same
name, so ``load(..., batch_size=4)`` style overrides work. The :class:`HierosConfig` is rebuilt from these
attributes in ``_setup_model`` (also on ``load``); ``policy_kwargs`` only takes the policy's own switches
(``decoded_subgoal_input``, ``bf16``, ``compile``). ``learning_rate`` (float or SB3 schedule) is the world models'
learning rate (all levels; the linear warm-up of ``world_model.warmup`` updates is applied on top).

Replay (one sequence replay per level, thesis 4.6.1)
----------------------------------------------------
Level 0's buffer is ``self.replay_buffer`` (:class:`~sb3_hieros.buffers.ETBSReplayBuffer` unless
``replay_buffer_class`` says otherwise; ``config.replay`` picks etbs/uniform/reference/count). It receives SB3's
transitions plus the subgoal in force. The buffers of levels 1..L-1 live in ``self.replay_buffer.higher_levels``, so
``save_replay_buffer`` / ``load_replay_buffer`` carry them; level i holds ``buffer_size // k**i`` steps. A row of
level i >= 1 (Dreamer view) is ``(o^i_t, a^i_{t-1}, r^i_t, is_first, is_terminal, g^{i+1}_t)`` with ``o^i_t`` the
concatenated last k world states of level i-1, ``a^i_{t-1}`` the subgoal it held before (stored as indices),
``r^i_t`` the **sum** of the environment rewards since its previous row (thesis 4.3.2: "the summed observed reward
of the k^i environment steps"; the reference stores the mean) and ``g^{i+1}_t`` the subgoal code in force from
level i+1.

When rows are written (global clock t, ``k = subgoal_interval``; see :mod:`sb3_hieros.policies`):

* at every update of level i: at ``t % k**i == 0`` for all envs (lock-step), and for env j at its episode start;
  an episode-start row has ``is_first`` and a history with every slot from before the reset zeroed;
* at an episode end of env j (``done``): the terminal observation (``infos[j]["terminal_observation"]``) is
  encoded bottom-up and every level i >= 1 writes a row for env j whose history ends with the terminal world state
  of level i-1, whose reward is the sum since its previous row **including the final reward**, and whose
  ``is_terminal`` is ``terminated`` (a time-limit truncation is not terminal). The next row of env j is the
  ``is_first`` row of its next episode.

This fixes the reference bugs of research note 8.4/8.5: the final reward is kept, ``is_first``/``is_terminal`` are
never lost at higher levels, one env's episode end never touches another env's reward sums, the k-step history
never straddles an episode border, and a new episode gets fresh subgoals at once instead of its predecessor's. An
episode start costs env j one extra (shorter) window at each level, so rows are written per env with the
buffers' per-stream write heads (``SequenceReplayBuffer.add_step(..., envs=...)``). The summed rewards are those the
agent sees (normalised under ``VecNormalize``, so the higher levels' replays are sampled without normalisation, while
level 0's stores raw rewards and normalises when sampling).

Training schedule
-----------------
``train_ratio`` is DreamerV3's replayed steps per environment step: level 0 makes
``train_ratio * n_envs / (batch_size * batch_length)`` updates per vec-env step (the fraction is carried over), and
level i >= 1 trains at every ``k**i``-th level-0 update (as the public code does) once its buffer can sample. No
update happens before ``learning_starts`` steps (uniformly random actions at every level until then, while the
hierarchy still encodes every observation) or while level 0's buffer cannot sample a chunk (e.g. right after
``load``).

Ablations (thesis 5.3; the switches are fields of :class:`HierosConfig`, listed in ``docs/ablations.md``): with
``hierarchical_world_models=False`` (5.3.1) only level 0 has a replay and every update trains all levels together in
level 0's imagination (:func:`~sb3_hieros.agent.shared.train_shared_hierarchy`); the ``reference`` section reproduces
the reference code's world-model action alignment (:func:`current_action_alignment`, applied to every level's
batch), its REINFORCE advantage and its zeroed terminal rewards.

Logging: SB3's ``rollout/*``, ``time/*``, ``train/learning_rate``, ``train/n_updates``, and
``train/level{i}/<metric>`` for every metric of :meth:`Subactor.train_step` (mean over the updates since the last
dump) plus ``train/level{i}/n_updates`` and ``train/level{i}/skipped_updates``.

Faults (see ``docs/resume.md`` for resuming a run)
--------------------------------------------------
* Non-finite observations (NaN/inf in a float observation, reset, step or terminal) and rewards raise ``ValueError``
  naming the env index (and the Dict key) before they reach the replay or the networks; SB3's ``VecCheckNan``
  wrapper works too (it also checks the actions).
* Each optimiser step of a level (world model, actor, critic, autoencoder) is skipped when its loss or gradient norm
  is not finite (:func:`~sb3_hieros.nn.guard.step_if_finite`): no parameter or optimiser state changes. The metrics
  ``train/level{i}/nonfinite/<name>`` give the fraction of skipped steps, ``train/level{i}/skipped_updates`` counts the
  updates with a skipped step, and ``max_nonfinite_updates`` such updates of one level in a row stop training with
  ``FloatingPointError`` naming the level and the loss.
* ``save`` and ``save_replay_buffer`` write atomically (a crash during a save leaves the previous file intact) with
  the sha256 of every member; ``load`` and ``load_replay_buffer`` refuse truncated, corrupted or changed files and
  saves of other algorithms with ``ValueError``, and a rejected replay leaves the model's replay as it was.
  ``load(..., safe=True)`` unpickles nothing (:mod:`sb3_hieros.save_util`).
* A warning estimates the replay memory of all levels before allocation when it exceeds the available memory.
"""

from __future__ import annotations

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
from stable_baselines3.common.type_aliases import GymEnv, MaybeCallback, Schedule

from sb3_hieros.agent.shared import train_shared_hierarchy
from sb3_hieros.buffers import (
    DictSequenceReplayBuffer,
    ETBSReplayBuffer,
    SequenceReplayBuffer,
    SequenceSamples,
    warn_if_replay_exceeds_memory,
)
from sb3_hieros.config import HierosConfig, get_preset
from sb3_hieros.policies import (
    CnnPolicy,
    HierarchyState,
    HierarchyStep,
    HierosPolicy,
    MlpPolicy,
    MultiInputPolicy,
    check_action_space,
    check_finite_observations,
    check_observation_space,
)
from sb3_hieros.replay_io import read_replay, write_replay
from sb3_hieros.save_util import prepare_model_load, qualified_name, safe_load_values, write_archive

__all__ = ["HIEROS", "current_action_alignment"]

SelfHIEROS = TypeVar("SelfHIEROS", bound="HIEROS")

# constructor keyword -> HierosConfig field (same name)
_CONFIG_KEYWORDS = (
    "buffer_size",
    "learning_starts",
    "batch_size",
    "batch_length",
    "train_ratio",
    "imag_horizon",
    "n_levels",
    "subgoal_interval",
    "etbs_temperature",
)


class _AddWithSubgoal:
    """Stand-in for level 0's buffer in ``OffPolicyAlgorithm._store_transition``: ``add`` also passes the subgoal,
    and with ``zero_terminal_reward`` stores the reward of a step that ends an episode as 0 (reference-compat switch
    ``reference.terminal_reward="zeroed"``, research note 8.4)."""

    def __init__(
        self, buffer: SequenceReplayBuffer, subgoal: np.ndarray | None, zero_terminal_reward: bool = False
    ) -> None:
        self.buffer = buffer
        self.subgoal = subgoal
        self.zero_terminal_reward = zero_terminal_reward

    def add(self, obs: Any, next_obs: Any, action: Any, reward: Any, done: Any, *args: Any, **kwargs: Any) -> None:
        if self.zero_terminal_reward:
            reward = np.where(np.asarray(done, dtype=bool).reshape(-1), 0.0, np.asarray(reward).reshape(-1))
        if self.subgoal is not None:
            kwargs["subgoal"] = self.subgoal
        self.buffer.add(obs, next_obs, action, reward, done, *args, **kwargs)


def current_action_alignment(samples: SequenceSamples, action_vectors: th.Tensor) -> SequenceSamples:
    """Samples whose row t carries a_t (the action chosen at o_t) instead of a_{t-1}: the reference code's world-model
    training alignment (reference-compat switch ``reference.action_alignment="current"``, research note 8.1).

    Row t gets row t+1's action; it is zero where row t is an episode start (as in the reference), where row t+1 is
    one (the action after a final observation) and in the chunk's last row (its a_t is not in the chunk).

    :param samples: a batch of chunks (B, T, ...)
    :param action_vectors: (B, T, A) the batch's actions a_{t-1} as float vectors (``Subactor.action_vectors``)
    :return: the samples with (B, T, A) float actions a_t
    """
    is_first = samples.is_first.bool()
    shifted = th.cat([action_vectors[:, 1:], th.zeros_like(action_vectors[:, :1])], 1)
    next_first = th.cat([is_first[:, 1:], th.zeros_like(is_first[:, :1])], 1)
    keep = ~(is_first | next_first)
    return samples._replace(actions=shifted * keep.unsqueeze(-1).to(shifted.dtype))


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
    :param batch_length: steps per chunk; None = preset
    :param train_ratio: replayed steps per environment step at level 0; None = preset
    :param imag_horizon: imagination horizon; None = preset
    :param n_levels: hierarchy depth (>= 1); None = preset
    :param subgoal_interval: k, steps of level i per action of level i+1; None = preset
    :param replay_buffer_class: level-0 buffer class, a :class:`SequenceReplayBuffer` subclass; None =
        :class:`ETBSReplayBuffer`
    :param replay_buffer_kwargs: extra keywords of the level-0 buffer
    :param etbs_temperature: tau of ETBS (eq. 4.21) at every level; None = preset
    :param config_overrides: changes to the preset (:meth:`HierosConfig.replace` keywords; nested sections as dicts)
    :param max_nonfinite_updates: training stops with ``FloatingPointError`` when this many updates in a row of one
        level had a non-finite loss or gradient (each such optimiser step is skipped, see the module docstring)
    :param policy_kwargs: keywords of the policy (``decoded_subgoal_input``, ``bf16``, ``compile``)
    :param stats_window_size: window of the rollout statistics
    :param tensorboard_log: tensorboard log directory
    :param verbose: 0 silent, 1 info, 2 debug
    :param seed: random seed
    :param device: torch device
    :param _init_setup_model: build the networks and buffers now
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
        batch_length: int | None = None,
        train_ratio: float | None = None,
        imag_horizon: int | None = None,
        n_levels: int | None = None,
        subgoal_interval: int | None = None,
        replay_buffer_class: type[SequenceReplayBuffer] | None = None,
        replay_buffer_kwargs: dict[str, Any] | None = None,
        etbs_temperature: float | None = None,
        config_overrides: dict[str, Any] | None = None,
        max_nonfinite_updates: int = 10,
        policy_kwargs: dict[str, Any] | None = None,
        stats_window_size: int = 100,
        tensorboard_log: str | None = None,
        verbose: int = 0,
        seed: int | None = None,
        device: th.device | str = "auto",
        _init_setup_model: bool = True,
    ) -> None:
        if config_overrides is not None and not isinstance(config_overrides, dict):
            raise ValueError(f"config_overrides must be a dict or None, got {type(config_overrides).__name__}")
        if policy_kwargs is not None and "config" in policy_kwargs:
            raise ValueError(
                "policy_kwargs must not contain 'config': HIEROS builds the policy's config from preset, "
                "config_overrides and its own keywords; put configuration changes into config_overrides"
            )
        if isinstance(max_nonfinite_updates, bool) or not isinstance(max_nonfinite_updates, int | np.integer):
            raise ValueError(f"max_nonfinite_updates must be an int >= 1, got {max_nonfinite_updates!r}")
        if max_nonfinite_updates < 1:
            raise ValueError(f"max_nonfinite_updates must be an int >= 1, got {max_nonfinite_updates!r}")
        base = get_preset(preset).replace(**(config_overrides or {}))
        given = {
            "buffer_size": buffer_size,
            "learning_starts": learning_starts,
            "batch_size": batch_size,
            "batch_length": batch_length,
            "train_ratio": train_ratio,
            "imag_horizon": imag_horizon,
            "n_levels": n_levels,
            "subgoal_interval": subgoal_interval,
            "etbs_temperature": etbs_temperature,
        }
        resolved = {name: getattr(base, name) if value is None else value for name, value in given.items()}
        super().__init__(
            policy,
            env,
            learning_rate=base.world_model.lr if learning_rate is None else learning_rate,
            buffer_size=resolved["buffer_size"],
            learning_starts=resolved["learning_starts"],
            batch_size=resolved["batch_size"],
            gamma=base.actor_critic.discount,
            train_freq=(1, "step"),
            gradient_steps=-1,
            replay_buffer_class=replay_buffer_class,
            replay_buffer_kwargs=replay_buffer_kwargs,
            optimize_memory_usage=False,
            policy_kwargs=policy_kwargs,
            stats_window_size=stats_window_size,
            tensorboard_log=tensorboard_log,
            verbose=verbose,
            device=device,
            support_multi_env=True,
            seed=seed,
            use_sde=False,
            sde_support=False,
            supported_action_spaces=(spaces.Discrete, spaces.Box),
        )
        self.preset = preset
        self.batch_length = resolved["batch_length"]
        self.train_ratio = resolved["train_ratio"]
        self.imag_horizon = resolved["imag_horizon"]
        self.n_levels = resolved["n_levels"]
        self.subgoal_interval = resolved["subgoal_interval"]
        self.etbs_temperature = resolved["etbs_temperature"]
        self.config_overrides = dict(config_overrides or {})
        self.max_nonfinite_updates = int(max_nonfinite_updates)
        self.config: HierosConfig | None = None
        # training-time hierarchy (built in _setup_learn, never saved)
        self._hier: HierarchyState | None = None
        self._reward_sums: list[np.ndarray] | None = None
        self._subgoal0: np.ndarray | None = None
        # update schedule (saved)
        self._update_budget = 0.0
        self._level_updates: list[int] | None = None
        # non-finite guard, per level: updates with a skipped optimiser step (total and current run of them)
        self._skipped_updates: list[int] | None = None
        self._nonfinite_streak: list[int] | None = None
        if getattr(self, "observation_space", None) is not None:
            check_observation_space(self.observation_space)
            check_action_space(self.action_space)
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
        """The configuration from preset, ``config_overrides`` and the keyword attributes (see module docstring)."""
        config = get_preset(self.preset).replace(**self.config_overrides)
        values = {name: getattr(self, name) for name in _CONFIG_KEYWORDS}
        return config.replace(**values, world_model={"lr": float(self.lr_schedule(1.0))})

    def _setup_model(self) -> None:
        self._setup_lr_schedule()
        self.set_random_seed(self.seed)
        check_observation_space(self.observation_space)
        check_action_space(self.action_space)
        self.config = self._build_config()
        self.gamma = self.config.actor_critic.discount
        self._convert_train_freq()
        self.policy = self.policy_class(
            self.observation_space,
            self.action_space,
            self.lr_schedule,
            config=self.config,
            **self.policy_kwargs,
        ).to(self.device)
        if self.replay_buffer is None:
            self.replay_buffer = self._make_replay_buffers()
        if self._level_updates is None or len(self._level_updates) != self.config.n_levels:
            self._level_updates = [0] * self.config.n_levels
        for name in ("_skipped_updates", "_nonfinite_streak"):
            if getattr(self, name, None) is None or len(getattr(self, name)) != self.config.n_levels:
                setattr(self, name, [0] * self.config.n_levels)
        self._hier = None
        self._reward_sums = None
        self._subgoal0 = None

    def _level_buffer_size(self, level: int) -> int:
        """Capacity of level ``level``'s replay: ``buffer_size // k**level``, at least one chunk per env stream."""
        assert self.config is not None
        size = self.buffer_size // self.config.subgoal_interval**level
        return size if level == 0 else max(size, self.config.batch_length * self.n_envs)

    def _make_replay_buffers(self) -> SequenceReplayBuffer:
        """Level 0's buffer with the buffers of levels 1..L-1 in its ``higher_levels`` attribute."""
        assert self.config is not None
        cfg = self.config
        buffer_class = self.replay_buffer_class or ETBSReplayBuffer
        if not (isinstance(buffer_class, type) and issubclass(buffer_class, SequenceReplayBuffer)):
            raise ValueError(
                f"replay_buffer_class must be a subclass of sb3_hieros.buffers.SequenceReplayBuffer, got {buffer_class}"
            )
        # one replay per level with a world model (only level 0's with hierarchical_world_models=False, 5.3.1)
        levels = [self.policy.subactor(i) for i in range(self._n_replays())]
        subgoal_shape = (levels[0].subgoal_dim,)
        etbs = {"temperature": cfg.etbs_temperature, "mode": cfg.replay}
        kwargs: dict[str, Any] = {
            "batch_length": cfg.batch_length,
            "subgoal_shape": subgoal_shape if cfg.n_levels > 1 else None,
        }
        if issubclass(buffer_class, ETBSReplayBuffer):
            kwargs.update(etbs)
        kwargs.update(self.replay_buffer_kwargs)
        contexts = [level.world_model.context_dim if cfg.replay_context else 0 for level in levels]
        # one warning for all levels together, before anything is allocated (then not again per buffer)
        spaces_per_level = [(self.observation_space, self.action_space)] + [
            (level.observation_space, level.action_space) for level in levels[1:]
        ]
        estimates = [
            SequenceReplayBuffer.estimate_nbytes(
                self._level_buffer_size(i),
                obs_space,
                act_space,
                self.n_envs,
                subgoal_shape if i < cfg.n_levels - 1 else None,
                contexts[i],
            )
            for i, (obs_space, act_space) in enumerate(spaces_per_level)
        ]
        warned = warn_if_replay_exceeds_memory(estimates, [f"level {i}" for i in range(len(levels))])
        with warnings.catch_warnings():
            if warned:
                warnings.filterwarnings("ignore", message="The replay buffer needs about")
            return self._allocate_replay_buffers(buffer_class, kwargs, levels, subgoal_shape, etbs, contexts)

    def _allocate_replay_buffers(
        self,
        buffer_class: type[SequenceReplayBuffer],
        kwargs: dict[str, Any],
        levels: list[Any],
        subgoal_shape: tuple[int, ...],
        etbs: dict[str, Any],
        contexts: list[int],
    ) -> SequenceReplayBuffer:
        """Build the buffers :meth:`_make_replay_buffers` planned (``contexts``: replay-context size per level)."""
        assert self.config is not None
        cfg = self.config
        buffer = buffer_class(
            self._level_buffer_size(0),
            self.observation_space,
            self.action_space,
            device=self.device,
            n_envs=self.n_envs,
            optimize_memory_usage=False,
            **({"context_dim": contexts[0]} if contexts[0] else {}),  # custom buffer classes may not know it
            **kwargs,
        )
        buffer.higher_levels = [  # type: ignore[attr-defined]
            ETBSReplayBuffer(
                self._level_buffer_size(i),
                levels[i].observation_space,
                levels[i].action_space,
                device=self.device,
                n_envs=self.n_envs,
                batch_length=cfg.batch_length,
                subgoal_shape=subgoal_shape if i < cfg.n_levels - 1 else None,
                context_dim=contexts[i],
                **etbs,
            )
            for i in range(1, len(levels))
        ]
        return buffer

    def _n_replays(self) -> int:
        """Levels with a replay of their own: all, or only level 0 with ``hierarchical_world_models=False``."""
        assert self.config is not None
        return self.config.n_levels if self.config.hierarchical_world_models else 1

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
        checksums) before anything is replaced; on ``ValueError`` the model's replay is unchanged.

        :param path: the file or a binary file object
        :param truncate_last_traj: unused (SB3's HER option)
        """
        buffers = read_replay(path, self.level_buffers())
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
        if fresh:
            self._reset_hierarchy()
        return result

    def _reset_hierarchy(self) -> None:
        """Fresh training-time hierarchy state for ``n_envs`` envs; every env starts an episode at its next step."""
        assert self.config is not None
        self._hier = self.policy.initial_hierarchy_state(self.n_envs)
        self._reward_sums = [np.zeros(self.n_envs, dtype=np.float64) for _ in range(self._n_replays())]
        self._subgoal0 = None
        self._last_episode_starts = np.ones(self.n_envs, dtype=bool)

    # ------------------------------------------------------------------------------------------------ acting

    def _sample_action(
        self, learning_starts: int, action_noise: Any = None, n_envs: int = 1
    ) -> tuple[np.ndarray, np.ndarray]:
        """One step of the hierarchy on ``self._last_obs`` (Algorithm 1) with exploration.

        Before ``learning_starts`` every level takes uniformly random actions, but every observation is still
        encoded so that the latent states and histories stay consistent. Afterwards the actors sample.

        :param learning_starts: steps of random warm-up
        :param action_noise: unsupported (must be None)
        :param n_envs: number of envs
        :return: environment action and buffer action (Box: scaled to [-1, 1]; Discrete: indices)
        """
        if action_noise is not None:
            raise ValueError("HIEROS explores with its stochastic actors; action_noise must be None")
        assert self._hier is not None and self._reward_sums is not None
        check_finite_observations(self._last_obs)  # type: ignore[arg-type]
        policy = self.policy
        obs, _ = policy.obs_to_tensor(self._last_obs)  # type: ignore[arg-type]
        is_first = th.as_tensor(np.asarray(self._last_episode_starts, dtype=bool), device=self.device)
        random_actions = policy.random_action_vectors(n_envs) if self.num_timesteps < learning_starts else None
        self._hier, step = policy.hierarchy_step(self._hier, obs, is_first, False, random_actions)
        self._write_update_rows(step, np.asarray(self._last_episode_starts, dtype=bool))
        self._subgoal0 = self._hier.actions[1].cpu().numpy() if len(self._hier.actions) > 1 else None
        vector = self._hier.actions[0]
        if isinstance(self.action_space, spaces.Box):
            buffer_action = vector.float().cpu().numpy()
            return policy.env_actions(vector), buffer_action
        action = policy.env_actions(vector)
        return action, action

    def _write_rows(
        self,
        level: int,
        envs: np.ndarray,
        obs: th.Tensor,
        prev_action: th.Tensor,
        is_first: np.ndarray,
        is_terminal: np.ndarray,
        subgoal: th.Tensor | None,
    ) -> None:
        """One row per env in ``envs`` of level ``level``'s buffer; resets those envs' reward sums.

        ``obs`` is the (m, w, D) history of lower world states the level observes (all or the newest, 5.3.6).
        """
        assert self._reward_sums is not None
        buffer = self.level_buffers()[level]
        obs_np = self.policy.higher_level_observation(obs).cpu().numpy()
        action = self.policy.subgoal_indices(level, prev_action)
        reward = self._reward_sums[level][envs].astype(np.float32)
        goal = None if subgoal is None else subgoal.cpu().numpy()
        # per-env rows at episode borders: the buffer keeps one write head per env stream
        buffer.add_step(obs_np, action, reward, is_first, is_terminal, goal, envs=envs)
        self._reward_sums[level][envs] = 0.0

    def _write_update_rows(self, step: HierarchyStep, is_first: np.ndarray) -> None:
        """Rows of the levels i >= 1 that updated at this step (lock-step updates and episode starts)."""
        assert self._hier is not None
        hier = self._hier
        for i in range(1, len(hier.latents)):
            updated = step.updated[i].cpu().numpy()
            envs = np.flatnonzero(updated)
            if envs.size == 0:
                continue
            index = th.as_tensor(envs, device=self.device)
            subgoal = hier.actions[i + 1][index] if i + 1 < len(hier.actions) else None
            self._write_rows(
                i,
                envs,
                hier.histories[i - 1][index],
                step.prev_actions[i][index],
                is_first[envs],
                np.zeros(envs.size, dtype=bool),
                subgoal,
            )

    @th.no_grad()
    def _write_terminal_rows(self, dones: np.ndarray, infos: list[dict[str, Any]]) -> None:
        """At episode ends: encode the terminal observation bottom-up and write every level's terminal row."""
        assert self._hier is not None
        hier, policy = self._hier, self.policy
        envs = np.flatnonzero(dones)
        index = th.as_tensor(envs, device=self.device)
        terminated = np.array([not infos[j].get("TimeLimit.truncated", False) for j in envs], dtype=bool)
        not_first = th.zeros(envs.size, dtype=th.bool, device=self.device)
        final = [infos[j].get("terminal_observation") for j in envs]
        encoded: th.Tensor | None = None
        if all(o is not None for o in final):
            if isinstance(final[0], dict):
                stacked: Any = {key: np.stack([o[key] for o in final]) for key in final[0]}
            else:
                stacked = np.stack(final)
            obs, _ = policy.obs_to_tensor(stacked)
            level0 = policy.subactor(0)
            latent = level0.observe_step(hier.latents[0].select(index), obs, hier.actions[0][index], not_first)
            encoded = level0.encoded_observation(latent)
        for i in range(1, len(hier.latents)):
            history = hier.histories[i - 1][index]  # (m, k, D)
            if encoded is not None:
                history = th.cat([history[:, 1:], encoded.unsqueeze(1)], 1)
            subgoal = hier.actions[i + 1][index] if i + 1 < len(hier.actions) else None
            self._write_rows(
                i, envs, history, hier.actions[i][index], np.zeros(envs.size, dtype=bool), terminated, subgoal
            )
            if encoded is not None and i + 1 < len(hier.latents):
                level = policy.subactor(i)
                obs_i = policy.higher_level_observation(history)
                latent = level.observe_step(hier.latents[i].select(index), obs_i, hier.actions[i][index], not_first)
                encoded = level.encoded_observation(latent)

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
        check_finite_observations(new_obs, "new observation")
        bad = np.flatnonzero(~np.isfinite(np.asarray(reward, dtype=np.float64).reshape(-1)))
        if bad.size:
            raise ValueError(
                f"reward of env {', '.join(str(j) for j in bad)} is not finite "
                f"({np.asarray(reward).reshape(-1)[bad].tolist()}); fix the environment or wrap the VecEnv in "
                "VecCheckNan(env, raise_exception=True)"
            )
        for j in np.flatnonzero(np.asarray(dones, dtype=bool).reshape(-1)):
            final = infos[j].get("terminal_observation")
            if final is not None:
                check_finite_observations(
                    {k: v[None] for k, v in final.items()} if isinstance(final, dict) else np.asarray(final)[None],
                    "terminal observation",
                    envs=[int(j)],
                )
        target: Any = replay_buffer
        if self._subgoal0 is not None or self._zero_terminal_reward():
            target = _AddWithSubgoal(replay_buffer, self._subgoal0, self._zero_terminal_reward())  # type: ignore[arg-type]
        super()._store_transition(target, buffer_action, new_obs, reward, dones, infos)
        assert self._reward_sums is not None
        for sums in self._reward_sums[1:]:
            sums += np.asarray(reward, dtype=np.float64).reshape(-1)
        done = np.asarray(dones, dtype=bool).reshape(-1)
        if self._zero_terminal_reward():  # reference: the pending sums are cleared before the terminal rows
            for sums in self._reward_sums[1:]:
                sums[done] = 0.0
        if done.any() and self._n_replays() > 1:
            self._write_terminal_rows(done, infos)
        self._last_episode_starts = done.copy()

    def _zero_terminal_reward(self) -> bool:
        """Reference-compat switch ``reference.terminal_reward="zeroed"`` (research note 8.4)."""
        return self.config is not None and self.config.reference.terminal_reward == "zeroed"

    # ------------------------------------------------------------------------------------------------ training

    def _prepare_samples(self, level: int, samples: SequenceSamples) -> SequenceSamples:
        """A sampled batch as level ``level`` trains on it: unchanged, or with the reference code's action alignment
        (``reference.action_alignment="current"``, :func:`current_action_alignment`)."""
        assert self.config is not None
        if self.config.reference.action_alignment == "previous":
            return samples
        vectors = self.policy.subactor(level).action_vectors(samples.actions, samples.is_first)
        return current_action_alignment(samples, vectors)

    def _record_level(self, level: int, metrics: dict[str, float]) -> None:
        """Log one update of ``level`` and watch its non-finite steps."""
        assert self._level_updates is not None
        self._level_updates[level] += 1
        for key, value in metrics.items():
            self.logger.record_mean(f"train/level{level}/{key}", value)
        self._count_nonfinite(level, metrics)

    def _set_world_model_lr(self, level: int, lr: float) -> None:
        """Schedule value times the warm-up factor of this level's update count on its world-model optimiser."""
        assert self._level_updates is not None
        sub = self.policy.subactor(level)
        updates = self._level_updates[level]
        scheduler = sub.wm_scheduler
        factor = 1.0
        if scheduler is not None:
            factor = float(scheduler.lr_lambdas[0](updates))  # type: ignore[attr-defined]
            scheduler.base_lrs = [lr] * len(sub.wm_optimizer.param_groups)
            scheduler.last_epoch = updates
        for group in sub.wm_optimizer.param_groups:
            group["lr"] = lr * factor

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
        k = cfg.subgoal_interval
        for _ in range(n_updates):
            count = self._level_updates[0]
            if not cfg.hierarchical_world_models:  # ablation 5.3.1: all levels in level 0's imagination
                self._set_world_model_lr(0, lr)
                samples = self._prepare_samples(0, buffers[0].sample(batch_size, env=self._vec_normalize_env))
                for i, metrics in enumerate(train_shared_hierarchy(self.policy.levels, samples, cfg)):
                    self._record_level(i, metrics)
                self._store_context(buffers[0], samples, 0)
                self._n_updates += 1
                continue
            for i, buffer in enumerate(buffers):
                if count % k**i != 0 or not buffer.can_sample():
                    continue
                self._set_world_model_lr(i, lr)
                samples = buffer.sample(batch_size, env=self._vec_normalize_env if i == 0 else None)
                metrics = self.policy.subactor(i).train_step(self._prepare_samples(i, samples))
                self._record_level(i, metrics)
                self._store_context(buffer, samples, i)
            self._n_updates += 1
        self.policy.set_training_mode(False)
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for i, count in enumerate(self._level_updates):
            self.logger.record(f"train/level{i}/n_updates", count, exclude="tensorboard")
        for i, count in enumerate(self._skipped_updates or []):
            self.logger.record(f"train/level{i}/skipped_updates", count)

    def _store_context(self, buffer: SequenceReplayBuffer, samples: SequenceSamples, level: int) -> None:
        """Hand level ``level``'s posterior states of the batch just trained on back to its replay (replay context)."""
        context = self.policy.subactor(level).last_context  # None unless the batch had a context
        if context is not None and samples.index is not None:
            buffer.store_context(samples.index, context)

    def _count_nonfinite(self, level: int, metrics: dict[str, float]) -> None:
        """Count an update of ``level`` with a skipped (non-finite) optimiser step; stop after too many in a row.

        :param level: the level that was just updated
        :param metrics: its :meth:`Subactor.train_step` metrics (``nonfinite/<name>`` = 1.0 for a skipped step)
        """
        assert self._skipped_updates is not None and self._nonfinite_streak is not None
        skipped = [key.split("/", 1)[1] for key, value in metrics.items() if key.startswith("nonfinite/") and value]
        if not skipped:
            self._nonfinite_streak[level] = 0
            return
        self._skipped_updates[level] += 1
        self._nonfinite_streak[level] += 1
        self.logger.record(f"train/level{level}/skipped_updates", self._skipped_updates[level])
        if self._nonfinite_streak[level] >= self.max_nonfinite_updates:
            prefixes = {"world_model": "wm", "actor": "actor", "critic": "critic", "autoencoder": "ae"}
            details = []
            for name in skipped:
                prefix = prefixes.get(name, name)
                values = [
                    f"{key}={metrics[key]:.4g}" for key in (f"{prefix}/loss", f"{prefix}/grad_norm") if key in metrics
                ]
                details.append(f"{name} loss ({', '.join(values)})" if values else f"{name} loss")
            raise FloatingPointError(
                f"level {level}: {self._nonfinite_streak[level]} updates in a row had a non-finite loss or gradient "
                f"(max_nonfinite_updates={self.max_nonfinite_updates}); last skipped: {'; '.join(details)}. The "
                "parameters were left at their last finite values; check the environment's observations and rewards, "
                "or lower the learning rates"
            )

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
        custom_objects = prepare_model_load(
            path,
            custom_objects,
            safe,
            env_spaces,
            HierosPolicy,
            {qualified_name(p): p for p in cls.policy_aliases.values()},  # type: ignore[misc]
            {qualified_name(b): b for b in (SequenceReplayBuffer, DictSequenceReplayBuffer, ETBSReplayBuffer)},  # type: ignore[misc]
        )
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
        return [*super()._excluded_save_params(), "config", "_hier", "_reward_sums", "_subgoal0"]

    def _get_torch_save_params(self) -> tuple[list[str], list[str]]:
        return ["policy", *(f"policy.{name}" for name in self.policy.optimizer_names())], []
