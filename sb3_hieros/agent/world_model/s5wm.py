"""S5WM (thesis 4.4): the world model whose sequence model is a stack of resettable S5 blocks."""

from __future__ import annotations

import contextlib

import torch as th
from torch import nn

from sb3_hieros.agent.world_model.base import ObsDict, WorldModel
from sb3_hieros.agent.world_model.latent import LatentState
from sb3_hieros.agent.world_model.layers import InputLayer, LayerNormGRUCell
from sb3_hieros.config import WorldModelConfig
from sb3_hieros.nn.distributions import symlog
from sb3_hieros.nn.networks import MLP, trunc_normal_init_, without_autocast
from sb3_hieros.nn.s5 import S5Stack, compile_s5

__all__ = ["S5WorldModel"]


class S5WorldModel(WorldModel):
    """S5WM (thesis 4.4): posterior from the observation alone, a stack of resettable S5 blocks as sequence model,
    ``h_t`` read out of the internal S5 states (thesis 5.3.5) and the prior from the stack output ``m_t``.

    With ``config.posterior="state"`` (not in the thesis) the posterior reads ``[h_t, e_t]`` as RSSM's does, so z_t
    carries what h_t did not predict rather than all of o_t; training then steps the stack through the chunk
    (:meth:`_observe_stepwise`) instead of scanning it in parallel.

    With ``config.deter_from == "gru"`` (not in the thesis), ``h_t = GRU(h_{t-1}, m_t)``: DreamerV3's GRU cell on the
    stack output keeps a non-linear recurrent state, and the prior reads ``h_t``, as RSSM's does. The S5 stack still
    runs as a parallel scan in training; the cell runs as a loop over the chunk (as RSSM's), and ``h_t`` is part of
    the replay context.

    :param observation_space: observation space of this level
    :param action_dim: size of the action vector
    :param config: world-model hyperparameters (``kind == "s5"``)
    :param bf16: bfloat16 autocast of the training loss (the S5 scan stays in fp32)
    :param compile: ``torch.compile`` the S5 stack's parallel scan (``sb3_hieros.nn.s5.compile_s5``; the step form
        used for acting and imagination stays eager)
    """

    kind = "s5"

    def _build_sequence_model(self, config: WorldModelConfig, compile: bool) -> None:
        c = config
        self.inp = InputLayer(self.stoch_dim, self.action_dim, c.s5_model_dim, c.action_input == "separate")
        self.sequence_model = S5Stack(c.s5_layers, c.s5_model_dim, c.s5_state_dim, c.s5_hippo_blocks, c.dropout)
        self._deter_in_context = c.deter_from == "gru"
        if self._deter_in_context:
            self.deter_cell = LayerNormGRUCell(c.s5_model_dim, self.deter_dim)
        else:
            readout_in = 2 * c.s5_layers * c.s5_state_dim if c.deter_from == "state" else c.s5_model_dim
            self.deter_out = nn.Linear(readout_in, self.deter_dim)
            trunc_normal_init_(self.deter_out)
        prior_in = self.deter_dim if self._deter_in_context else c.s5_model_dim
        self.prior_net = MLP(prior_in, self.stoch_dim, c.hidden, layers=1)
        self._posterior_in_loop = c.posterior_reads_state
        if self._posterior_in_loop:
            self._build_split_posterior(c.hidden)
        else:
            self.post_net = MLP(self.embed_dim, self.stoch_dim, c.hidden, layers=1)
        if compile:
            # the S5 module's own opt-in: real-split parallel scan under torch.compile; the step form stays eager
            compile_s5(self.sequence_model)

    def reuse_step_weights(self) -> contextlib.AbstractContextManager:
        return self.sequence_model.reuse_step_weights()

    def no_weight_decay_parameters(self) -> list[nn.Parameter]:
        """SSM parameters of the S5 stack (Lambda, B, Delta) plus all 1-d parameters.

        :return: list of parameters
        """
        params = {id(p): p for p in self.sequence_model.ssm_parameters()}
        params.update({id(p): p for p in super().no_weight_decay_parameters()})
        return list(params.values())

    def _initial_state(self, batch_size: int) -> LatentState:
        uniform = self._uniform_logits(batch_size)
        return LatentState(
            stoch=th.zeros(batch_size, self.stoch_dim, device=self.device),
            deter=th.zeros(batch_size, self.deter_dim, device=self.device),
            seq=self.sequence_model.initial_state(batch_size, self.device),
            logits=uniform,
            prior_logits=uniform,
        )

    def _deterministic_state(self, seq: th.Tensor, out: th.Tensor) -> th.Tensor:
        """h_t = symlog(Linear([Re x_t, Im x_t] of all layers)) (thesis 5.3.5) or symlog(Linear(m_t)).

        :param seq: (..., L, P) complex S5 states
        :param out: (..., H) stack output m_t
        :return: (..., D) float32
        """
        source = th.view_as_real(seq).flatten(-3) if self.config.deter_from == "state" else out
        return symlog(self.deter_out(source).float())

    def _gru_deterministic_states(self, out: th.Tensor, keep: th.Tensor, deter: th.Tensor) -> th.Tensor:
        """h_t = GRU(h_{t-1}, m_t) over a chunk (``deter_from="gru"``), in float32 like RSSM's loop.

        :param out: (B, T, H) stack outputs m_t
        :param keep: (B, T, 1) 0 where an episode starts (h_{t-1} is dropped there)
        :param deter: (B, D) h before the first step
        :return: (B, T, D)
        """
        deters = []
        with without_autocast(out.device.type):
            for m_t, k_t in zip(out.float().unbind(1), keep.float().unbind(1), strict=True):
                deter = self.deter_cell(m_t, deter * k_t)
                deters.append(deter)
        return th.stack(deters, 1)

    def _observe(
        self, obs: ObsDict, actions: th.Tensor, is_first: th.Tensor, state: LatentState | None, deterministic: bool
    ) -> tuple[LatentState, th.Tensor]:
        if self._posterior_in_loop:
            return self._observe_stepwise(obs, actions, is_first, state, deterministic)
        batch, length = actions.shape[:2]
        embed = self._embed(obs, (batch, length))  # (B, T, E)
        post_raw = self.post_net(embed)
        stoch, post_logits = self._draw(post_raw, deterministic)  # (B, T, G*K), (B, T, G, K)
        first_prev = th.zeros_like(stoch[:, :1]) if state is None else state.stoch.unsqueeze(1)
        prev_stoch = th.cat([first_prev, stoch[:, :-1]], 1)  # z_{t-1}
        keep = (~is_first).unsqueeze(-1).to(stoch.dtype)  # (B, T, 1)
        u = self.inp(prev_stoch * keep, actions * keep)  # (B, T, H)
        out, seq = self.sequence_model._forward(u.float(), is_first, None if state is None else state.seq)
        if self._deter_in_context:
            start = th.zeros(batch, self.deter_dim, device=out.device) if state is None else state.deter
            deter = self._gru_deterministic_states(out, keep, start)  # (B, T, D)
            prior_raw = self.prior_net(deter)
        else:
            deter = self._deterministic_state(seq, out)  # (B, T, D)
            prior_raw = self.prior_net(out)
        prior_logits = self._normalise(prior_raw)
        return LatentState(stoch, deter, seq, post_logits, prior_logits), prior_logits

    def _observe_stepwise(
        self, obs: ObsDict, actions: th.Tensor, is_first: th.Tensor, state: LatentState | None, deterministic: bool
    ) -> tuple[LatentState, th.Tensor]:
        """:meth:`_observe` with a posterior that reads h_t (``config.posterior="state"``): z_t depends on h_t, which
        depends on z_{t-1}, so the S5 stack runs in step form over the chunk (one discretisation for the chunk, in
        the graph), as the RSSM runs its GRU; what does not depend on the loop is computed outside it.
        """
        batch, length = actions.shape[:2]
        state = self.initial_state(batch) if state is None else state
        embed = self._embed(obs, (batch, length))  # (B, T, E)
        keep = (~is_first).unsqueeze(-1).to(actions.dtype)  # (B, T, 1)
        embed_pre = self.post_embed(embed).float()  # (B, T, hidden)
        action_pre = self.inp.action_features(actions * keep).float()  # (B, T, .)
        stoch, deter, seq = state.stoch, state.deter, state.seq
        stochs, deters, seqs, outs, logits = [], [], [], [], []
        with without_autocast(embed.device.type), self.reuse_step_weights():
            steps = zip(embed_pre.unbind(1), action_pre.unbind(1), keep.unbind(1), is_first.unbind(1), strict=True)
            for e_t, a_t, k_t, first_t in steps:
                out, seq = self.sequence_model._step(self.inp.join(stoch * k_t, a_t), seq, first_t)
                if self._deter_in_context:
                    deter = self.deter_cell(out, deter * k_t)
                else:
                    deter = self._deterministic_state(seq, out)
                stoch, post_logits = self._draw(self._split_posterior(deter, e_t), deterministic)
                stochs.append(stoch)
                deters.append(deter)
                seqs.append(seq)
                outs.append(out)
                logits.append(post_logits)
        deter_seq = th.stack(deters, 1)  # (B, T, D)
        prior_raw = self.prior_net(deter_seq if self._deter_in_context else th.stack(outs, 1))
        prior_logits = self._normalise(prior_raw)
        post = LatentState(th.stack(stochs, 1), deter_seq, th.stack(seqs, 1), th.stack(logits, 1), prior_logits)
        return post, prior_logits

    def _prior_step(
        self, state: LatentState, action: th.Tensor, reset: th.Tensor | None
    ) -> tuple[th.Tensor, th.Tensor, th.Tensor]:
        """(m_t, h_t) = f(h_{t-1}, z_{t-1}, a_{t-1}) in step form; returns deter, S5 states and raw prior logits."""
        stoch, keep = state.stoch, None
        if reset is not None:
            keep = (~reset).unsqueeze(-1).to(stoch.dtype)
            stoch, action = stoch * keep, action * keep
        u = self.inp(stoch, action)
        out, seq = self.sequence_model._step(u, state.seq, reset)
        if self._deter_in_context:  # h_{t-1} is memory only here, so only here is it dropped at a reset
            deter = self.deter_cell(out, state.deter if keep is None else state.deter * keep)
            return deter, seq, self.prior_net(deter)
        return self._deterministic_state(seq, out), seq, self.prior_net(out)

    def _obs_step(
        self, state: LatentState, obs: ObsDict, action: th.Tensor, is_first: th.Tensor, deterministic: bool
    ) -> LatentState:
        batch = int(action.shape[0])
        deter, seq, prior_raw = self._prior_step(state, action, is_first)
        embed = self._embed(obs, (batch,))
        if self._posterior_in_loop:
            post_raw = self._split_posterior(deter, self.post_embed(embed))
        else:
            post_raw = self.post_net(embed)
        stoch, post_logits = self._draw(post_raw, deterministic)
        return LatentState(stoch, deter, seq, post_logits, self._normalise(prior_raw))

    def _img_step(self, state: LatentState, action: th.Tensor, deterministic: bool) -> tuple[LatentState, th.Tensor]:
        deter, seq, prior_raw = self._prior_step(state, action, None)
        stoch, prior_logits = self._draw(prior_raw, deterministic)
        return LatentState(stoch, deter, seq, prior_logits, prior_logits), prior_logits
