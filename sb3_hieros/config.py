"""Hyperparameters of HIEROS as dataclasses, with the presets ``"paper"`` and ``"small"``.

``"paper"`` is thesis section 4.6.3 (Mattes 2023), completed where the table is silent with the values of the
paper-time runs of the public reference code. ``"small"`` keeps
every code path and shrinks the widths so that a CPU learns CartPole in minutes.

Every value not given explicitly to :class:`~sb3_hieros.HIEROS` comes from the chosen preset.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

WORLD_MODEL_KINDS = ("s5", "rssm")
DETER_SOURCES = ("state", "output", "gru")
ACTION_INPUTS = ("joint", "separate")
POSTERIOR_INPUTS = ("auto", "observation", "state")
IMAG_GRADIENTS = ("auto", "reinforce", "dynamics")
HIGHER_LEVEL_INPUTS = ("all", "last")
EXTRINSIC_REWARD_LEVELS = ("all", "top")
ACTION_ALIGNMENTS = ("previous", "current")
REINFORCE_ADVANTAGES = ("normalized", "raw")
TERMINAL_REWARDS = ("kept", "zeroed")
RETURN_NORMALIZATIONS = ("combined", "per_term")
#: Which critic values pass gradient to the actions under dynamics backpropagation (``ActorCriticConfig``).
VALUE_GRADIENTS = ("all", "returns", "none")
#: Which critic's values form the lambda-returns and the baseline of the actor-critic (``ActorCriticConfig``).
RETURN_CRITICS = ("fast", "slow")


def _check_types(obj: object) -> None:
    """Raise ``ValueError`` naming the field and value when a value does not have its field's type: ``int`` fields
    take integers (not floats such as ``16.0``, not bools), ``float`` fields finite real numbers (not NaN or inf, not
    bools), ``bool`` fields bools. Runs first in every section's ``__post_init__``, so the range checks after it
    compare numbers."""
    for f in dataclasses.fields(obj):  # type: ignore[arg-type]
        value, name = getattr(obj, f.name), f"{type(obj).__name__}.{f.name}"
        if f.type == "int" and (isinstance(value, bool) or not isinstance(value, numbers.Integral)):
            raise ValueError(f"{name} must be an integer, got {value!r} ({type(value).__name__})")
        if f.type == "float" and (
            isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value)
        ):
            raise ValueError(f"{name} must be a finite number, got {value!r} ({type(value).__name__})")
        if f.type == "bool" and not isinstance(value, bool):
            raise ValueError(f"{name} must be a bool, got {value!r} ({type(value).__name__})")


def _check_positive(obj: object, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not isinstance(value, int | float) or isinstance(value, bool) or value <= 0:
            raise ValueError(f"{type(obj).__name__}.{name} must be a positive number, got {value!r}")


def _check_non_negative(obj: object, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not isinstance(value, int | float) or isinstance(value, bool) or value < 0:
            raise ValueError(f"{type(obj).__name__}.{name} must be a number >= 0, got {value!r}")


def _check_choice(obj: object, name: str, choices: tuple[str, ...]) -> None:
    value = getattr(obj, name)
    if value not in choices:
        raise ValueError(f"{type(obj).__name__}.{name} must be one of {choices}, got {value!r}")


def _check_fraction(obj: object, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{type(obj).__name__}.{name} must lie in [0, 1], got {value!r}")


@dataclass
class WorldModelConfig:
    """World model of one level (thesis 4.4, eq. 4.10-4.13).

    :param kind: ``"s5"`` (S5WM, default) or ``"rssm"`` (DreamerV3's GRU world model, ablation 5.3.2)
    :param s5_layers: number of S5 blocks in the sequence model (thesis: 8; ablation 5.3.7: 4)
    :param s5_model_dim: S5 model width H
    :param s5_state_dim: S5 complex state size P
    :param s5_hippo_blocks: HiPPO-N initialisation blocks J
    :param dropout: dropout inside the S5 blocks
    :param deter_dim: size of the deterministic state h_t
    :param deter_from: ``"state"``: h_t read out from the S5 internal states (thesis 5.3.5, default);
        ``"output"``: h_t from the stack output m_t; ``"gru"``: h_t = GRU(h_{t-1}, m_t), a DreamerV3 GRU cell on the
        stack output, and the prior reads h_t instead of m_t (not in the thesis; see the continuous-control results)
    :param action_input: how z_{t-1} and a_{t-1} enter the sequence model: ``"joint"``: one Linear over ``[z, a]``,
        then LayerNorm and SiLU (thesis, first DreamerV3); ``"separate"``: z and a each through their own Linear,
        LayerNorm and SiLU, concatenated (half the width each), so the action keeps a normalised share of the input
        however large z is (later DreamerV3 releases; not in the thesis)
    :param posterior: what the posterior ``q(z_t | .)`` reads: ``"observation"``: the embedding e_t alone (the
        thesis' S5WM, whose training scans the whole chunk in parallel); ``"state"``: ``[h_t, e_t]`` (DreamerV3's RSSM),
        so z_t holds what h_t did not predict; S5WM then runs its stack step by step over the chunk in training, as
        the RSSM runs its GRU; ``"auto"``: ``"observation"`` for S5WM, ``"state"`` for RSSM
    :param stoch_groups: number of categorical latents in z_t
    :param stoch_classes: classes per categorical latent
    :param hidden: width of the prior/posterior/input layers
    :param cnn_depth: channels of the first conv layer (doubled per stage)
    :param image_shift: random-shift augmentation of image observations in world-model training: each training
        chunk's frames move together by up to this many pixels (border pixels repeated), as the encoder's input and
        the decoder's target; 0 (default) trains on the images as they are. Not in the thesis or DreamerV3 (DrQ's
        augmentation, held over each chunk; see the continuous-control results)
    :param mlp_units: width of the MLP encoder/decoder for vector observations
    :param mlp_layers: depth of the MLP encoder/decoder
    :param head_units: width of the reward and continue heads
    :param head_layers: depth of the reward and continue heads
    :param unimix: uniform mixture of the categorical latents
    :param reward_scale: weight of the reward head's negative log-likelihood in the prediction loss (eq. 4.11); 1
        (default) as in the thesis and DreamerV3. Above 1 the representation is pulled harder towards what predicts
        the reward, against the image decoder's sum over pixels (see the continuous-control results)
    :param reward_overshoot: open-loop reward prediction in the world-model loss: from every posterior state of a
        chunk the prior is rolled this many steps under the replayed actions, and the reward head is trained on the
        replayed reward of each step it reaches within the episode (mean negative log-likelihood over those steps,
        weighted by ``reward_scale``); 0 (default) trains the reward head on posterior states only, as the thesis and
        DreamerV3 do. Not in the thesis or DreamerV3 (multi-step reward prediction as in MuZero and TD-MPC; see the
        continuous-control results)
    :param prior_decoder_scale: weight of a second image/observation reconstruction in the world-model loss, decoded
        from the one-step prior state (h_t with z drawn from the prior p(z^_t | m_t) instead of the posterior): the
        observation at t is then predicted from what came before it (the last state and action), which needs the
        motion, not only the frame. 0 (default) decodes from posterior states only, as the thesis and DreamerV3
        do; costs one more decoder pass an update. Not in the thesis or DreamerV3 (see the continuous-control
        results)
    :param dyn_scale: weight of the dynamics KL (alpha_dyn, eq. 4.10)
    :param rep_scale: weight of the representation KL (alpha_rep, eq. 4.10)
    :param free_bits: free nats of both KL terms (eq. 4.12, 4.13)
    :param lr: learning rate of the world model optimiser (AdamW)
    :param eps: AdamW epsilon
    :param grad_clip: gradient norm clip
    :param weight_decay: AdamW weight decay (never applied to the S5 SSM parameters)
    :param warmup: linear learning-rate warm-up in updates
    """

    kind: str = "s5"
    s5_layers: int = 8
    s5_model_dim: int = 256
    s5_state_dim: int = 128
    s5_hippo_blocks: int = 4
    dropout: float = 0.1
    deter_dim: int = 256
    deter_from: str = "state"
    action_input: str = "joint"
    posterior: str = "auto"
    stoch_groups: int = 32
    stoch_classes: int = 32
    hidden: int = 256
    cnn_depth: int = 24
    image_shift: int = 0
    mlp_units: int = 512
    mlp_layers: int = 2
    head_units: int = 256
    head_layers: int = 2
    unimix: float = 0.01
    reward_scale: float = 1.0
    reward_overshoot: int = 0
    prior_decoder_scale: float = 0.0
    dyn_scale: float = 0.5
    rep_scale: float = 0.1
    free_bits: float = 1.0
    lr: float = 1e-4
    eps: float = 1e-8
    grad_clip: float = 1000.0
    weight_decay: float = 0.0
    warmup: int = 1000

    def __post_init__(self) -> None:
        _check_types(self)
        _check_choice(self, "kind", WORLD_MODEL_KINDS)
        _check_choice(self, "deter_from", DETER_SOURCES)
        _check_choice(self, "action_input", ACTION_INPUTS)
        _check_choice(self, "posterior", POSTERIOR_INPUTS)
        _check_positive(
            self,
            "s5_layers",
            "s5_model_dim",
            "s5_state_dim",
            "s5_hippo_blocks",
            "deter_dim",
            "stoch_groups",
            "stoch_classes",
            "hidden",
            "cnn_depth",
            "mlp_units",
            "mlp_layers",
            "head_units",
            "head_layers",
            "eps",
            "grad_clip",
        )
        _check_non_negative(self, "lr")  # 0 freezes the world model (rl-zoo's enjoy loads with learning_rate=0)
        _check_fraction(self, "dropout", "unimix")
        if self.s5_state_dim % self.s5_hippo_blocks:
            raise ValueError(
                f"WorldModelConfig.s5_state_dim ({self.s5_state_dim}) must be divisible by "
                f"s5_hippo_blocks ({self.s5_hippo_blocks})"
            )
        _check_non_negative(self, "image_shift", "reward_scale", "reward_overshoot", "prior_decoder_scale")
        if self.weight_decay < 0 or self.warmup < 0 or self.free_bits < 0:
            raise ValueError(
                "WorldModelConfig.weight_decay, warmup and free_bits must be >= 0, got "
                f"{self.weight_decay!r}, {self.warmup!r}, {self.free_bits!r}"
            )

    @property
    def posterior_reads_state(self) -> bool:
        """Whether the posterior reads h_t besides the observation (``posterior`` with ``"auto"`` resolved)."""
        if self.posterior == "auto":
            return self.kind == "rssm"
        return self.posterior == "state"


@dataclass
class ActorCriticConfig:
    """Actor and the three critics of one level (thesis 4.3.2, eq. 4.3, 4.6-4.9).

    :param units: width of actor and critic MLPs
    :param layers: depth of actor and critic MLPs
    :param discount: gamma of the lambda-returns
    :param lambda_: lambda of the lambda-returns
    :param entropy: entropy bonus eta (eq. 4.9)
    :param unimix: uniform mixture of categorical actions
    :param extrinsic_weight: weight of the extrinsic reward term (eq. 4.3)
    :param subgoal_weight: weight alpha_g of the subgoal reward term (eq. 4.3)
    :param novelty_weight: weight alpha_nov of the novelty reward term (eq. 4.3)
    :param actor_extras: feed reward, continue and prior entropy to actor and critics (eq. 4.6; ablation 5.3.11)
    :param imag_gradient: ``"reinforce"``, ``"dynamics"`` or ``"auto"`` (REINFORCE for discrete actions and
        subgoals, dynamics backpropagation for Box actions)
    :param actor_lr: actor learning rate (the public code's 3e-5; the thesis table's 1e-4 is the world model's)
    :param critic_lr: critic learning rate
    :param eps: AdamW epsilon of actor and critics
    :param grad_clip: gradient norm clip of actor and critics
    :param slow_critic_fraction: EMA fraction of the slow critics, applied every update
    :param return_normalization: ``"combined"`` (default): the advantage is the weighted sum of the terms'
        advantages divided by one return scale, that of the mixed return of eq. 4.3, so each term pulls on the actor
        in proportion to its weight and its size in reward units; ``"per_term"`` (the public HIEROS code): each term's
        advantage is divided by its own return scale, so each term's pull is set by its weight alone
        (:class:`~sb3_hieros.agent.actor_critic.ActorCritic`)
    :param value_gradient: with dynamics backpropagation, which of the critics' values pass gradient to the
        imagined actions: ``"all"`` (default, DreamerV3's code): the values in the lambda-returns and the baseline
        v(s_t) the advantage subtracts; ``"returns"``: the baseline is held fixed, so the actor climbs the
        lambda-returns (DreamerV2's dynamics objective); ``"none"``: every value is held fixed, so the gradient comes
        through the imagined rewards of the horizon alone (:class:`~sb3_hieros.agent.actor_critic.ActorCritic`).
        REINFORCE is unaffected
    :param return_critic: which copy of each critic values the imagined states in the lambda-returns and the baseline:
        ``"fast"`` (default, DreamerV3's code) or ``"slow"``, its EMA copy (the thesis' baseline, eq. 4.9, and
        DreamerV2's target critic). Under dynamics backpropagation the actor then follows the input gradient of a
        critic averaged over recent updates (:class:`~sb3_hieros.agent.actor_critic.ActorCritic`)
    :param replay_value_loss: weight of DreamerV3's replay value loss (its later releases: 0.3; not in the thesis):
        each critic also regresses lambda-returns along the replayed sequences, computed from the recorded rewards
        and bootstrapped with the imagined returns
        (:meth:`~sb3_hieros.agent.actor_critic.ActorCritic.replay_value_loss`). 0 (default) trains the critics on
        imagination alone, as the thesis does. Needs ``hierarchical_world_models=True``
    """

    units: int = 256
    layers: int = 2
    discount: float = 0.997
    lambda_: float = 0.95
    entropy: float = 3e-4
    unimix: float = 0.01
    extrinsic_weight: float = 1.0
    subgoal_weight: float = 0.3
    novelty_weight: float = 0.1
    actor_extras: bool = True
    imag_gradient: str = "auto"
    actor_lr: float = 3e-5
    critic_lr: float = 3e-5
    eps: float = 1e-5
    grad_clip: float = 100.0
    slow_critic_fraction: float = 0.02
    return_normalization: str = "combined"
    value_gradient: str = "all"
    return_critic: str = "fast"
    replay_value_loss: float = 0.0

    def __post_init__(self) -> None:
        _check_types(self)
        _check_positive(self, "units", "layers", "actor_lr", "critic_lr", "eps", "grad_clip")
        _check_choice(self, "return_normalization", RETURN_NORMALIZATIONS)
        _check_fraction(self, "discount", "lambda_", "unimix", "slow_critic_fraction")
        _check_choice(self, "imag_gradient", IMAG_GRADIENTS)
        _check_choice(self, "value_gradient", VALUE_GRADIENTS)
        _check_choice(self, "return_critic", RETURN_CRITICS)
        for name in ("entropy", "extrinsic_weight", "subgoal_weight", "novelty_weight", "replay_value_loss"):
            if getattr(self, name) < 0:
                raise ValueError(f"ActorCriticConfig.{name} must be >= 0, got {getattr(self, name)!r}")


@dataclass
class SubgoalConfig:
    """Subgoal autoencoder of one level (thesis 4.3.1, eq. 4.1-4.2).

    :param n_cat: number of categorical subgoal variables (thesis: 8)
    :param n_classes: classes per subgoal variable (thesis: 8)
    :param units: width of encoder and decoder MLPs
    :param layers: depth of encoder and decoder MLPs
    :param beta: weight of the KL to the uniform prior (eq. 4.2)
    :param lr: learning rate
    :param eps: AdamW epsilon
    :param grad_clip: gradient norm clip
    """

    n_cat: int = 8
    n_classes: int = 8
    units: int = 256
    layers: int = 2
    beta: float = 0.5
    lr: float = 1e-4
    eps: float = 1e-6
    grad_clip: float = 100.0

    def __post_init__(self) -> None:
        _check_types(self)
        _check_positive(self, "n_cat", "n_classes", "units", "layers", "lr", "eps", "grad_clip")
        if self.beta < 0:
            raise ValueError(f"SubgoalConfig.beta must be >= 0, got {self.beta!r}")


@dataclass
class ReferenceCompatConfig:
    """Switches that reproduce behaviours of the public reference code which this package corrects by default.

    The defaults are the corrected behaviours (``docs/design.md`` lists the differences). Set all three with
    ``config_overrides={"reference": REFERENCE_BEHAVIOUR}`` (see :data:`REFERENCE_BEHAVIOUR`).

    :param action_alignment: ``"previous"`` (default): the world model's sequence model at row t consumes
        ``(z_{t-1}, a_{t-1})`` in training, acting and imagination alike. ``"current"``: in world-model training
        row t consumes ``(z_{t-1}, a_t)``, the action chosen *after* seeing o_t (the reference's
        ``observe`` pairs z_{t-1} with a_t while acting and imagination use a_{t-1}; a_t is zeroed where
        ``is_first``). The last row of a chunk, whose a_t the chunk does not hold, gets a zero action.
    :param reinforce_advantage: ``"normalized"`` (default): REINFORCE uses the weighted sum of the per-term
        advantages, each divided by its return scale, as dynamics backpropagation does (DreamerV3). ``"raw"``:
        REINFORCE uses the reward-weight-weighted *average* of the unnormalised advantages
        ``sum_k w_k (R^k - v^k) / sum_k w_k``; dynamics backpropagation is unchanged.
    :param terminal_reward: ``"kept"`` (default): the reward of the step that ends an episode is stored. ``"zeroed"``:
        it is stored as 0 at level 0, and the terminal rows of the higher levels store a reward of 0 (the reference
        clears the pending reward sum before writing them). The reference's wiping of *every* env's pending
        sums at any env's reset is not reproduced.
    """

    action_alignment: str = "previous"
    reinforce_advantage: str = "normalized"
    terminal_reward: str = "kept"

    def __post_init__(self) -> None:
        _check_choice(self, "action_alignment", ACTION_ALIGNMENTS)
        _check_choice(self, "reinforce_advantage", REINFORCE_ADVANTAGES)
        _check_choice(self, "terminal_reward", TERMINAL_REWARDS)


#: ``config_overrides={"reference": REFERENCE_BEHAVIOUR}`` reproduces all three reference behaviours at once.
REFERENCE_BEHAVIOUR: dict[str, str] = {
    "action_alignment": "current",
    "reinforce_advantage": "raw",
    "terminal_reward": "zeroed",
}


@dataclass
class HierosConfig:
    """Everything a HIEROS agent needs besides the environment.

    :param world_model: world model of every level
    :param actor_critic: actor-critic of every level
    :param subgoal: subgoal autoencoder of every level
    :param n_levels: hierarchy depth (thesis: 3; ablation 5.3.4)
    :param subgoal_interval: k, steps of level i between two actions of level i+1 (thesis: 4)
    :param batch_size: chunks per update
    :param batch_length: steps per chunk
    :param imag_horizon: imagination horizon
    :param imag_start_fraction: fraction of the ``batch_size * batch_length`` posterior states of a batch that start
        an imagination rollout, drawn uniformly without replacement at every update; 1.0 (default, thesis and
        DreamerV3): all of them. Fewer starts make the actor-critic half of an update cheaper (a CPU lever)
    :param train_ratio: replayed steps per environment step at level 0 (DreamerV3's train ratio)
    :param world_model_updates: world-model updates per update of a level (Algorithm 2 step 1): 1 (default, thesis)
        is the update on the batch the level then imagines from; each further one comes before it, on a batch of its
        own, so the world model learns ``world_model_updates`` times as much replay per actor-critic update
    :param buffer_size: replay capacity of level 0 in steps (higher levels get ``buffer_size // k**i``)
    :param learning_starts: environment steps of random actions before training starts
    :param actor_learning_starts: environment steps before the actors and critics start learning and acting; 0
        (default, thesis): at ``learning_starts`` with the world models. Above ``learning_starts`` only the world
        models learn in between, and every level keeps acting uniformly at random as in the warm-up, so the actors
        start from world models that have learnt for longer (an actor that learns from a world model of a few
        hundred updates settles on one push for every state: ``docs/results/control.md``)
    :param etbs_temperature: tau of ETBS (thesis 4.5, eq. 4.21)
    :param replay: ``"etbs"`` (default), ``"uniform"``, ``"reference"`` or ``"count"`` (ablation 5.3.3)
    :param replay_context: False (default, thesis and reference code): every sampled chunk starts the world model
        from zeros, so training sees at most ``batch_length`` steps of history while acting carries the state over
        whole episodes. True: each level's replay keeps the posterior state of every trained row and a chunk starts
        from the state stored for the row before it (DreamerV3's replay context; :mod:`sb3_hieros.buffers`), at
        :meth:`~sb3_hieros.agent.world_model.WorldModel.context_dim` floats per stored step
    :param hierarchical_world_models: True (default): every level has its own world model and imagines in it
        (hierarchical imagination). False (ablation 5.3.1): only level 0 has a world model; level i >= 1 observes the
        last ``k**i`` world states of level 0 and all levels are trained together in level 0's imagination, where
        level i acts every ``k**i`` imagined steps (see :mod:`sb3_hieros.agent.shared`)
    :param higher_level_input: ``"all"`` (default): level i+1 observes the last k world states of level i
        concatenated; ``"last"`` (ablation 5.3.6): only the newest (k-th) of them
    :param decoded_subgoal_input: the actor and critics of a level below the top see the subgoal decoded into their
        own h space instead of the one-hot code (ablation 5.3.8; ``policy_kwargs={"decoded_subgoal_input": True}``
        is an alias)
    :param update_subgoals_in_imagination: False (default): a level's imagination holds the subgoal of each replay
        row fixed over the horizon. True (ablation 5.3.9): every k imagined steps the level above observes the last
        k imagined states (with its own world model) and proposes a new subgoal
    :param extrinsic_reward_levels: ``"all"`` (default): every level's actor-critic gets the extrinsic reward term;
        ``"top"`` (ablation 5.3.10): only the top level, the levels below learn from subgoal and novelty rewards
    :param reference: behaviours of the public reference code (:class:`ReferenceCompatConfig`)
    """

    world_model: WorldModelConfig = field(default_factory=WorldModelConfig)
    actor_critic: ActorCriticConfig = field(default_factory=ActorCriticConfig)
    subgoal: SubgoalConfig = field(default_factory=SubgoalConfig)
    n_levels: int = 3
    subgoal_interval: int = 4
    batch_size: int = 16
    batch_length: int = 64
    imag_horizon: int = 16
    imag_start_fraction: float = 1.0
    train_ratio: float = 1024.0
    world_model_updates: int = 1
    buffer_size: int = 1_000_000
    learning_starts: int = 1024
    actor_learning_starts: int = 0
    etbs_temperature: float = 0.3
    replay: str = "etbs"
    replay_context: bool = False
    hierarchical_world_models: bool = True
    higher_level_input: str = "all"
    decoded_subgoal_input: bool = False
    update_subgoals_in_imagination: bool = False
    extrinsic_reward_levels: str = "all"
    reference: ReferenceCompatConfig = field(default_factory=ReferenceCompatConfig)

    def __post_init__(self) -> None:
        _check_types(self)
        _check_positive(
            self, "n_levels", "subgoal_interval", "batch_size", "batch_length", "imag_horizon", "train_ratio"
        )
        _check_positive(self, "buffer_size", "world_model_updates")
        fraction = self.imag_start_fraction
        if not isinstance(fraction, int | float) or isinstance(fraction, bool) or not 0.0 < fraction <= 1.0:
            raise ValueError(f"HierosConfig.imag_start_fraction must be in (0, 1], got {self.imag_start_fraction!r}")
        _check_non_negative(self, "learning_starts", "actor_learning_starts")
        _check_fraction(self, "etbs_temperature")
        _check_choice(self, "replay", ("etbs", "uniform", "reference", "count"))
        _check_choice(self, "higher_level_input", HIGHER_LEVEL_INPUTS)
        _check_choice(self, "extrinsic_reward_levels", EXTRINSIC_REWARD_LEVELS)
        for name in (
            "replay_context",
            "hierarchical_world_models",
            "decoded_subgoal_input",
            "update_subgoals_in_imagination",
        ):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"HierosConfig.{name} must be a bool, got {getattr(self, name)!r}")
        self._check_ablation_combinations()

    def _check_ablation_combinations(self) -> None:
        """Raise ``ValueError`` for ablation switches that cannot apply to this configuration (thesis 5.3)."""
        defaults = {
            "hierarchical_world_models": True,
            "higher_level_input": "all",
            "decoded_subgoal_input": False,
            "update_subgoals_in_imagination": False,
            "extrinsic_reward_levels": "all",
        }
        if self.n_levels == 1:
            changed = [f"{name}={getattr(self, name)!r}" for name, v in defaults.items() if getattr(self, name) != v]
            if changed:
                raise ValueError(
                    f"HierosConfig: {', '.join(changed)} needs a hierarchy, but n_levels=1: with a single level there "
                    "is no higher level, no subgoal and no top-only reward; use n_levels >= 2 or leave these switches "
                    "at their defaults"
                )
            return
        k, horizon = self.subgoal_interval, self.imag_horizon
        if not self.hierarchical_world_models:
            if self.actor_critic.replay_value_loss > 0:
                raise ValueError(
                    f"HierosConfig: actor_critic.replay_value_loss={self.actor_critic.replay_value_loss!r} needs "
                    "hierarchical_world_models=True (the higher levels of the shared world model have no replayed "
                    "states of their own); set it to 0 or use hierarchical world models"
                )
            if self.update_subgoals_in_imagination:
                raise ValueError(
                    "HierosConfig: update_subgoals_in_imagination=True is implied by hierarchical_world_models=False "
                    "(all levels act in level 0's imagination, the higher ones every k**i steps); leave it False"
                )
            if horizon < k ** (self.n_levels - 1):
                raise ValueError(
                    f"HierosConfig: hierarchical_world_models=False trains level i in level 0's imagination with one "
                    f"step every k**i imagined steps, so imag_horizon ({horizon}) must be >= k**(n_levels-1) = "
                    f"{k ** (self.n_levels - 1)} (k={k}, n_levels={self.n_levels})"
                )
        if self.update_subgoals_in_imagination and horizon < k:
            raise ValueError(
                f"HierosConfig: update_subgoals_in_imagination=True re-plans the subgoal every k={k} imagined steps, "
                f"but imag_horizon={horizon} < k would never do so"
            )
        ac = self.actor_critic
        if self.extrinsic_reward_levels == "top" and ac.subgoal_weight <= 0 and ac.novelty_weight <= 0:
            raise ValueError(
                "HierosConfig: extrinsic_reward_levels='top' leaves the levels below the top only the subgoal and "
                "novelty rewards, but actor_critic.subgoal_weight and novelty_weight are both 0"
            )
        if self.reference.reinforce_advantage == "raw" and ac.imag_gradient == "dynamics":
            raise ValueError(
                "HierosConfig: reference.reinforce_advantage='raw' changes the REINFORCE advantage, but "
                "actor_critic.imag_gradient='dynamics' uses no REINFORCE at any level; use 'auto' or 'reinforce'"
            )

    def replace(self, **changes: Any) -> HierosConfig:
        """A copy with top-level fields replaced; nested sections take a dict of their own fields.

        :param changes: e.g. ``n_levels=2, world_model={"s5_layers": 4}, reference={"terminal_reward": "zeroed"}``
        :return: the new configuration (validated)
        """
        top = {f.name for f in dataclasses.fields(self)}
        unknown = set(changes) - top
        if unknown:
            raise ValueError(f"unknown HierosConfig fields {sorted(unknown)}; expected some of {sorted(top)}")
        resolved: dict[str, Any] = {}
        for name, value in changes.items():
            current = getattr(self, name)
            if dataclasses.is_dataclass(current) and isinstance(value, dict):
                names = {f.name for f in dataclasses.fields(current)}
                bad = set(value) - names
                if bad:
                    raise ValueError(
                        f"unknown {type(current).__name__} fields {sorted(bad)}; expected some of {sorted(names)}"
                    )
                value = dataclasses.replace(current, **value)
            resolved[name] = value
        return dataclasses.replace(self, **resolved)


def paper_config() -> HierosConfig:
    """Thesis table 4.6.3 (about 37M parameters for 18 Atari actions)."""
    return HierosConfig()


def small_config() -> HierosConfig:
    """A CPU preset: same code paths, 2 S5 blocks, narrower widths, a lower train ratio.

    Chosen for learning speed per CPU second on CartPole-v1 (``benchmarks/sample_efficiency.py``; the README has the
    comparisons): a larger world-model learning rate (1e-3) and 16-step chunks, imagination from half of the posterior
    states of a batch (``imag_start_fraction``), and an actor-critic that departs from the thesis values (no novelty
    term, discount 0.99, critics at 1e-3 with a slow-critic EMA of 0.1, actor at 1e-4), so that the critics keep up
    with a policy that improves within a few thousand steps. The replay context (``replay_context=True``, about 2 KB of
    replay per stored step) lets training see states with as much history as acting does.

    h_t is a GRU state on the S5 stack output (``world_model.deter_from="gru"``, not in the thesis, whose S5WM reads
    h_t out of the S5 internal states): the S5 blocks update their states linearly, and on continuous control the
    world model then barely resolves how one action changes the motion; the GRU's non-linear update does. With
    bfloat16 losses the agent ends 10k steps of DMC cartpole-balance and Pendulum-v1 higher; in float32 it ends level
    and rises earlier on cartpole-balance; CartPole-v1 stays at or above 470 (docs, continuous-control results). The
    ``"paper"`` preset keeps the thesis' readout.

    Each level update trains its world model twice (``world_model_updates=2``: once more before the update it imagines
    from, on a batch of its own): on continuous control the policy improves only as far as the world model has learned
    what its actions do, and a second world-model update per actor-critic update lifts DMC cartpole-balance from
    proprioception and from pixels while CartPole-v1 and Pendulum-v1 stay above their marks (docs, CPU suite and
    continuous-control results). It costs up to a fifth more time on vector observations and 1.6 times the time on
    64x64 images; ``config_overrides={"world_model_updates": 1}`` restores one update.
    """
    return HierosConfig(
        world_model=WorldModelConfig(
            s5_layers=2,
            s5_model_dim=128,
            s5_state_dim=64,
            s5_hippo_blocks=2,
            dropout=0.0,
            deter_dim=128,
            deter_from="gru",
            stoch_groups=16,
            stoch_classes=16,
            hidden=128,
            cnn_depth=16,
            mlp_units=256,
            head_units=128,
            lr=1e-3,
            warmup=100,
        ),
        actor_critic=ActorCriticConfig(
            units=128,
            actor_lr=1e-4,
            critic_lr=1e-3,
            discount=0.99,
            slow_critic_fraction=0.1,
            novelty_weight=0.0,
        ),
        subgoal=SubgoalConfig(units=128),
        n_levels=2,
        batch_size=16,
        batch_length=16,
        imag_start_fraction=0.5,
        train_ratio=64.0,
        world_model_updates=2,
        buffer_size=100_000,
        learning_starts=500,
        replay_context=True,
    )


PRESETS = {"paper": paper_config, "small": small_config}


def config_from_dict(config: Mapping[str, Any] | HierosConfig | None) -> HierosConfig:
    """A :class:`HierosConfig` from its ``dataclasses.asdict`` form (what a saved policy holds), or the paper preset.

    :param config: a HierosConfig, a dict of its fields (nested sections as dicts), or None for the ``"paper"`` preset
    :return: the configuration
    """
    if config is None:
        return get_preset("paper")
    if isinstance(config, HierosConfig):
        return config
    if not isinstance(config, Mapping):
        raise ValueError(f"config must be a HierosConfig, a dict of its fields or None, got {type(config).__name__}")
    sections = {
        "world_model": WorldModelConfig,
        "actor_critic": ActorCriticConfig,
        "subgoal": SubgoalConfig,
        "reference": ReferenceCompatConfig,
    }
    names = {f.name for f in dataclasses.fields(HierosConfig)}
    unknown = set(config) - names
    if unknown:
        raise ValueError(f"config has unknown fields {sorted(unknown)}; expected some of {sorted(names)}")
    values = dict(config)
    for name, cls in sections.items():
        if name in values and isinstance(values[name], Mapping):
            values[name] = cls(**values[name])
    return HierosConfig(**values)


def get_preset(name: str) -> HierosConfig:
    """The configuration of a named preset.

    :param name: ``"paper"`` or ``"small"``
    :return: a fresh :class:`HierosConfig`
    """
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; expected one of {sorted(PRESETS)}")
    return PRESETS[name]()
