"""DreamerV3's recurrent state-space model (RSSM) behind the S5WM interface (ablation 5.3.2)."""

from __future__ import annotations

from collections.abc import Callable

import torch as th

from sb3_hieros.agent.world_model.base import ObsDict, WorldModel
from sb3_hieros.agent.world_model.latent import LatentState
from sb3_hieros.agent.world_model.layers import InputLayer, LayerNormGRUCell
from sb3_hieros.config import WorldModelConfig
from sb3_hieros.nn.networks import MLP, without_autocast

__all__ = ["RSSMWorldModel"]


class RSSMWorldModel(WorldModel):
    """DreamerV3's recurrent state-space model behind the same interface (ablation 5.3.2).

    ``h_t = GRU(h_{t-1}, Inp(z_{t-1}, a_{t-1}))``, posterior ``q(z_t | h_t, e_t)`` (``q(z_t | e_t)`` with
    ``config.posterior="observation"``), prior ``p(z^_t | h_t)``. The GRU state is the deterministic state (``seq``
    and ``deter`` are the same tensor). The GRU reads the sampled z_{t-1}, so :meth:`observe` runs a time loop;
    everything that does not depend on the loop is hoisted out of it.

    :param observation_space: observation space of this level
    :param action_dim: size of the action vector
    :param config: world-model hyperparameters (``kind == "rssm"``; the S5 fields are unused)
    :param bf16: bfloat16 autocast of the training loss (outside the time loop)
    :param compile: ``torch.compile`` the loop cell
    """

    kind = "rssm"
    _deter_is_seq = True

    def _build_sequence_model(self, config: WorldModelConfig, compile: bool) -> None:
        c = config
        self.inp = InputLayer(self.stoch_dim, self.action_dim, c.hidden, c.action_input == "separate")
        self.gru = LayerNormGRUCell(c.hidden, self.deter_dim)
        self.prior_net = MLP(self.deter_dim, self.stoch_dim, c.hidden, layers=1)
        self._build_split_posterior(c.hidden)
        self._cell: Callable[..., tuple[th.Tensor, th.Tensor]] = self._cell_eager
        if compile:
            self._cell = th.compile(self._cell_eager)

    def _initial_state(self, batch_size: int) -> LatentState:
        deter = th.zeros(batch_size, self.deter_dim, device=self.device)
        uniform = self._uniform_logits(batch_size)
        return LatentState(th.zeros(batch_size, self.stoch_dim, device=self.device), deter, deter, uniform, uniform)

    def _cell_eager(
        self, stoch: th.Tensor, action_pre: th.Tensor, deter: th.Tensor, embed_pre: th.Tensor
    ) -> tuple[th.Tensor, th.Tensor]:
        """One loop step: GRU update and raw posterior logits (the part that cannot leave the loop).

        :param stoch: (B, G*K) z_{t-1} (already zeroed where reset)
        :param action_pre: (B, .) the action's part of the input, ``InputLayer.action_features(a_{t-1})``
        :param deter: (B, D) h_{t-1} (already zeroed where reset)
        :param embed_pre: (B, hidden) embedding half of the posterior layer
        :return: h_t (B, D) and raw posterior logits (B, G*K)
        """
        x = self.inp.join(stoch, action_pre)
        deter = self.gru(x, deter)
        return deter, self._split_posterior(deter, embed_pre)

    def _observe(
        self, obs: ObsDict, actions: th.Tensor, is_first: th.Tensor, state: LatentState | None, deterministic: bool
    ) -> tuple[LatentState, th.Tensor]:
        batch, length = actions.shape[:2]
        state = self.initial_state(batch) if state is None else state
        embed = self._embed(obs, (batch, length))
        keep = (~is_first).unsqueeze(-1).to(actions.dtype)  # (B, T, 1)
        # hoisted out of the loop (under a bf16 autocast, these run in bf16 and are taken back to float32)
        embed_pre = self.post_embed(embed).float()  # (B, T, hidden)
        action_pre = self.inp.action_features(actions * keep).float()  # (B, T, .)
        stoch, deter = state.stoch, state.deter
        stochs, deters, logits = [], [], []
        with without_autocast(embed.device.type):  # the recurrent state stays in float32
            for e_t, a_t, k_t in zip(embed_pre.unbind(1), action_pre.unbind(1), keep.unbind(1), strict=True):
                deter, post_raw = self._cell(stoch * k_t, a_t, deter * k_t, e_t)
                stoch, post_logits = self._draw(post_raw, deterministic)
                stochs.append(stoch)
                deters.append(deter)
                logits.append(post_logits)
        deter_seq = th.stack(deters, 1)  # (B, T, D)
        prior_raw = self.prior_net(deter_seq)  # hoisted
        prior_logits = self._normalise(prior_raw)
        post = LatentState(th.stack(stochs, 1), deter_seq, deter_seq, th.stack(logits, 1), prior_logits)
        return post, prior_logits

    def _obs_step(
        self, state: LatentState, obs: ObsDict, action: th.Tensor, is_first: th.Tensor, deterministic: bool
    ) -> LatentState:
        batch = int(action.shape[0])
        keep = (~is_first).unsqueeze(-1).to(action.dtype)
        embed = self._embed(obs, (batch,))
        embed_pre = self.post_embed(embed)
        deter, post_raw = self._cell(
            state.stoch * keep, self.inp.action_features(action * keep), state.deter * keep, embed_pre
        )
        stoch, post_logits = self._draw(post_raw, deterministic)
        prior_raw = self.prior_net(deter)
        return LatentState(stoch, deter, deter, post_logits, self._normalise(prior_raw))

    def _img_step(self, state: LatentState, action: th.Tensor, deterministic: bool) -> tuple[LatentState, th.Tensor]:
        deter = self.gru(self.inp(state.stoch, action), state.deter)
        prior_raw = self.prior_net(deter)
        stoch, prior_logits = self._draw(prior_raw, deterministic)
        return LatentState(stoch, deter, deter, prior_logits, prior_logits), prior_logits
