"""SB3 callbacks that show what HIEROS plans and what its world model imagines.

* :class:`SubgoalDecodeCallback`: the current subgoal of every level above 0, decoded down to the environment's
  observation space (thesis 4.3.2, last paragraph; Figs 5.5, 5.6, 5.9), next to the real observation: images as a
  grid, vectors as labelled bars per entry and, where the env can draw a given state (gymnasium's classic-control
  tasks, :class:`ClassicControlRenderer`, or a user's ``renderer``), as the frame of the subgoal beside the real one.
* :class:`ImaginationCallback`: a recent real chunk of level 0's replay against the world model's open-loop
  imagination with the recorded actions, and the per-step prediction error (thesis Fig. 5.1).

Both write PNGs under ``save_dir`` and, when the model's logger has a TensorBoard output (``tensorboard_log``), SB3
``Image`` values to it. The reward terms of every level (extrinsic, subgoal, novelty; Fig. 5.3) need no callback:
:class:`~sb3_hieros.HIEROS` logs them as ``train/level{i}/reward/<term>`` (means over the updates since the last
dump).

Cost and side effects. Between two of its ``every`` steps a callback only compares two integers. When it draws, it
runs under ``torch.no_grad`` with the policy in evaluation mode (modes restored afterwards), draws nothing at random
(posterior and prior modes), never samples from a replay buffer (it reads the newest rows directly), and restores
the global random states of torch (CPU and initialised CUDA devices), numpy (which the replay samplers use) and
Python's ``random`` afterwards. So training with and without these callbacks gives the same parameters under the
same seed (tested).

Images go to TensorBoard straight through the logger's TensorBoard output at the current step (not through
``logger.record``, which keeps only the last value of a key until the next dump, so images drawn between two dumps
would be lost, and which would have other output formats reject the image).

Rendering needs matplotlib (the ``extra`` dependencies); it is imported when a callback is created.
"""

from __future__ import annotations

import contextlib
import os
import pathlib
import random
import warnings
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import Image, TensorBoardOutputFormat

from sb3_hieros.agent.world_model import LatentState, WorldModel
from sb3_hieros.buffers import SequenceReplayBuffer
from sb3_hieros.rendering import (
    CLASSIC_CONTROL_OBSERVATIONS,
    ClassicControlRenderer,
    ObservationLayout,
    Renderer,
    display_image,
    figure_pixels,
    new_figure,
    observation_labels,
    require_matplotlib,
    subgoal_picture,
    task_name,
)
from sb3_hieros.type_aliases import Observation

__all__ = [
    "CLASSIC_CONTROL_OBSERVATIONS",
    "ClassicControlRenderer",
    "ImaginationCallback",
    "ObservationLayout",
    "SubgoalDecodeCallback",
    "imagine_open_loop",
    "observation_labels",
    "recent_window",
]

#: Where a callback writes its PNGs (None: TensorBoard only).
SaveDir = str | os.PathLike | None
#: Observation entries of at most this many dimensions are shown in the vector plots of ImaginationCallback.
MAX_PLOTTED_DIMS = 16


# ----------------------------------------------------------------------------------------------------------------------
# Decoding and imagination (no RL bookkeeping)
# ----------------------------------------------------------------------------------------------------------------------


def recent_window(buffer: SequenceReplayBuffer, env: int, context: int, horizon: int) -> np.ndarray | None:
    """Rows of the newest ``context + horizon`` consecutive steps of one env stream whose last ``horizon`` steps lie
    in one episode (no episode start there; the context may cross an episode start, the world model resets there).

    Reads the stream's bookkeeping only: no random numbers are drawn.

    :param buffer: a sequence replay buffer (level 0's)
    :param env: index of the env stream
    :param context: steps to condition on (>= 1)
    :param horizon: steps to imagine (>= 1)
    :return: (context + horizon,) row indices in time order, or None when no such window is stored
    """
    if not 0 <= env < buffer.n_envs:
        raise ValueError(f"env must lie in [0, {buffer.n_envs}), got {env}")
    length = context + horizon
    stored = int(buffer.stored_steps()[env])
    if stored < length:
        return None
    order = (int(buffer.oldest_rows()[env]) + np.arange(stored)) % buffer.buffer_size  # (stored,) oldest first
    starts = np.concatenate([[0], np.cumsum(buffer.is_first[order, env], dtype=np.int64)])
    first = np.arange(stored - length + 1)  # candidate window starts
    clean = starts[first + length] - starts[first + context] == 0  # no episode start in the imagined part
    valid = np.flatnonzero(clean)
    if valid.size == 0:
        return None
    begin = int(valid[-1])
    return order[begin : begin + length]


@th.no_grad()
def imagine_open_loop(
    world_model: WorldModel,
    observations: Observation,
    prev_actions: th.Tensor,
    is_first: th.Tensor,
    context: int,
) -> tuple[Observation, Observation]:
    """A world model on a real chunk: posterior over the first ``context`` steps, then open-loop imagination of the
    remaining steps with the recorded actions (thesis 4.4.3, Fig. 5.1; :meth:`WorldModel.rollout`). Modes instead of
    samples.

    :param world_model: e.g. level 0's, ``model.policy.hierarchy.levels[0].world_model``
    :param observations: (B, T, *obs_shape) (a dict of them for Dict spaces), as the model sees them (normalised
        under VecNormalize)
    :param prev_actions: (B, T, A) float action vectors, row t = a_{t-1} (the action that led to o_t)
    :param is_first: (B, T) bool episode starts
    :param context: number of observed steps C, 1 <= C < T
    :return: reconstructions of the context (B, C, ...) and imagined observations (B, T - C, ...), images as float
        pixels in [0, 255]
    """
    length = int(is_first.shape[1])
    if not 1 <= context < length:
        raise ValueError(f"context must lie in [1, {length}) for chunks of {length} steps, got {context}")
    if isinstance(observations, Mapping):
        seen: Observation = {key: value[:, :context] for key, value in observations.items()}
    else:
        seen = observations[:, :context]
    post, _ = world_model.observe(seen, prev_actions[:, :context], is_first[:, :context], deterministic=True)

    def recorded(t: int, state: LatentState) -> th.Tensor | None:
        # row C + t holds a_{C+t-1}, which leads from s_{C+t-1} to s_{C+t}
        return prev_actions[:, context + t] if context + t < length else None

    start = post.select((slice(None), context - 1))  # (B,)
    states, _ = world_model.rollout(start, length - context, recorded, deterministic=True)
    imagined = states.select(slice(1, None)).map_fields(lambda x: x.transpose(0, 1))  # (B, T - C)
    return world_model.decode(post), world_model.decode(imagined)


# ----------------------------------------------------------------------------------------------------------------------
# Isolation from training
# ----------------------------------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _isolated(policy: th.nn.Module) -> Iterator[None]:
    """No gradients, evaluation mode, and the global random states of torch, numpy and ``random`` restored."""
    py_state = random.getstate()
    np_state = np.random.get_state()  # noqa: NPY002 (the replay samplers draw from numpy's global state)
    torch_state = th.get_rng_state()
    cuda_states = th.cuda.get_rng_state_all() if th.cuda.is_available() and th.cuda.is_initialized() else None
    modes = [(module, module.training) for module in policy.modules()]
    try:
        policy.train(False)
        with th.no_grad():
            yield
    finally:
        for module, mode in modes:
            module.training = mode
        random.setstate(py_state)
        np.random.set_state(np_state)  # noqa: NPY002
        th.set_rng_state(torch_state)
        if cuda_states is not None:
            th.cuda.set_rng_state_all(cuda_states)


def _as_numpy_dict(obs: Any, keys: list[str], is_dict: bool) -> dict[str, np.ndarray]:
    """Observation(s) as a key -> float numpy dict (tensors moved to the CPU)."""
    items = obs if is_dict else {keys[0]: obs}
    out = {}
    for key in keys:
        value = items[key]
        array = value.detach().float().cpu().numpy() if isinstance(value, th.Tensor) else np.asarray(value)
        out[key] = array.astype(np.float32)
    return out


# ----------------------------------------------------------------------------------------------------------------------
# Callbacks
# ----------------------------------------------------------------------------------------------------------------------


class _PeriodicDrawingCallback(BaseCallback):
    """Shared part: argument checks, the ``every`` schedule, isolation, PNG and TensorBoard output.

    :param every: draw when the number of environment steps reaches a multiple of ``every`` (at most once per
        vec-env step)
    :param save_dir: directory for the PNGs (created), or None
    :param tensorboard: also write the images to the logger's TensorBoard output (if it has one)
    :param verbose: 0 silent, 1 prints the written files
    """

    def __init__(self, every: int, save_dir: str | os.PathLike | None, tensorboard: bool, verbose: int) -> None:
        super().__init__(verbose)
        if isinstance(every, bool) or not isinstance(every, int | np.integer) or every < 1:
            raise ValueError(f"every must be a positive int (environment steps), got {every!r}")
        if save_dir is not None and not isinstance(save_dir, str | os.PathLike):
            raise ValueError(f"save_dir must be a path or None, got {type(save_dir).__name__}")
        if not isinstance(tensorboard, bool):
            raise ValueError(f"tensorboard must be a bool, got {tensorboard!r}")
        if save_dir is None and not tensorboard:
            raise ValueError("save_dir is None and tensorboard is False: the callback would write nothing")
        require_matplotlib()
        self.every = int(every)
        self.save_dir = None if save_dir is None else pathlib.Path(save_dir)
        self.tensorboard = tensorboard
        #: PNG files written so far, in order
        self.saved_files: list[pathlib.Path] = []
        self._next_draw = self.every
        self._disabled = False

    def _init_callback(self) -> None:
        from sb3_hieros.hieros import HIEROS

        if not isinstance(self.model, HIEROS):
            raise ValueError(f"{type(self).__name__} works with HIEROS models, got {type(self.model).__name__}")
        self._next_draw = (self.num_timesteps // self.every + 1) * self.every
        if self.save_dir is not None:
            self.save_dir.mkdir(parents=True, exist_ok=True)

    def _on_step(self) -> bool:
        if self._disabled or self.num_timesteps < self._next_draw:
            return True
        self._next_draw = (self.num_timesteps // self.every + 1) * self.every
        with _isolated(self.model.policy):
            self._draw()
        return True

    def _draw(self) -> None:
        raise NotImplementedError

    def _write_image(self, tag: str, image: np.ndarray, filename: str) -> None:
        """PNG under ``save_dir`` and an SB3 ``Image`` on every TensorBoard output of the logger, at this step."""
        if self.save_dir is not None:
            from matplotlib.image import imsave

            path = self.save_dir / filename
            imsave(path, image)
            self.saved_files.append(path)
            if self.verbose >= 1:
                print(f"{type(self).__name__}: wrote {path}")
        if self.tensorboard:
            for output in self.logger.output_formats:
                if isinstance(output, TensorBoardOutputFormat):
                    output.write({tag: Image(image, "HWC")}, {tag: None}, self.num_timesteps)


class SubgoalDecodeCallback(_PeriodicDrawingCallback):
    """Every ``every`` environment steps, decode the current subgoal of every level above 0 into the environment's
    observation space (:meth:`HIEROS.decoded_subgoals`, thesis 4.3.2) and show it next to the real observation.

    One picture per shown env, with one column per level (observation | level-1 subgoal | level-2 subgoal ...):
    image observations as a grid with one row per image key (thesis Fig. 5.5); vector and discrete observations (the
    decoded value of a discrete entry is its most likely one) as bars per entry,
    labelled with the entry's name (``labels``, else :data:`CLASSIC_CONTROL_OBSERVATIONS` for gymnasium's
    classic-control tasks, else ``obs[i]``), and, when a ``renderer`` draws states, a row of frames: the real state
    and every decoded subgoal as the env would show them. The real observation is the one the hierarchy has just
    encoded (:meth:`HIEROS.decoded_subgoals`, normalised under VecNormalize like the decoded ones; the bars show these
    values, the renderer gets them in the env's units). PNGs are named ``subgoals_<step>_env<j>.png``, TensorBoard tags
    ``subgoals/env<j>``. A one-level model has no subgoals: the callback warns once and does nothing.

    :param every: environment steps between two pictures
    :param n_envs_shown: how many envs (the first ones) to show; at most the model's ``n_envs``
    :param save_dir: directory for the PNGs, or None
    :param tensorboard: also write to the logger's TensorBoard output
    :param labels: names of the entries of a vector observation (a sequence for a Box space, a dict key -> sequence
        for Dict spaces), or None for the known names of classic-control tasks and ``obs[i]`` otherwise
    :param renderer: ``"auto"`` draws the frames of gymnasium's classic-control tasks
        (:class:`ClassicControlRenderer`; without pygame it warns once and shows the bars only); a callable draws
        one observation (in the env's units; a dict for Dict spaces) as an (H, W, 3) uint8 frame; None shows no
        frames. Only for observation spaces without images.
    :param verbose: 0 silent, 1 prints the written files
    """

    def __init__(
        self,
        every: int,
        n_envs_shown: int = 1,
        save_dir: SaveDir = None,
        tensorboard: bool = True,
        labels: Sequence[str] | Mapping[str, Sequence[str]] | None = None,
        renderer: Renderer | str | None = "auto",
        verbose: int = 0,
    ) -> None:
        super().__init__(every, save_dir, tensorboard, verbose)
        if isinstance(n_envs_shown, bool) or not isinstance(n_envs_shown, int | np.integer) or n_envs_shown < 1:
            raise ValueError(f"n_envs_shown must be a positive int, got {n_envs_shown!r}")
        if isinstance(labels, str) or not (labels is None or isinstance(labels, Sequence | Mapping)):
            raise ValueError(f"labels must be a sequence of names, a dict key -> names, or None; got {labels!r}")
        if not (renderer is None or renderer == "auto" or callable(renderer)):
            raise ValueError(f"renderer must be 'auto', a callable or None, got {renderer!r}")
        self.n_envs_shown = int(n_envs_shown)
        self.labels = labels
        self.renderer = renderer
        self._warned = False
        #: observation key -> the names of its entries (set when training starts)
        self.entry_labels: dict[str, list[str]] = {}
        self._state_renderer: Renderer | None = None

    def _init_callback(self) -> None:
        super()._init_callback()
        if self.n_envs_shown > self.model.n_envs:
            raise ValueError(f"n_envs_shown={self.n_envs_shown} exceeds the model's n_envs={self.model.n_envs}")
        self._disabled = self.model.policy.hierarchy.n_levels < 2
        if self._disabled and not self._warned:
            warnings.warn(
                "SubgoalDecodeCallback: the model has n_levels=1, so there are no subgoals to decode; the callback "
                "does nothing",
                UserWarning,
                stacklevel=2,
            )
            self._warned = True
        spec = self.model.policy.hierarchy.levels[0].world_model.spec
        env_id = self._env_id()
        given = self.labels
        if spec.is_dict and given is not None and not isinstance(given, Mapping):
            raise ValueError(f"labels for a Dict observation space must be a dict key -> names, got {given!r}")
        if not spec.is_dict and isinstance(given, Mapping):
            raise ValueError(f"labels for a Box observation space must be a sequence of names, got {given!r}")
        if isinstance(given, Mapping) and set(given) - set(spec.entry_keys):
            raise ValueError(
                f"labels name keys {sorted(set(given) - set(spec.entry_keys))} that are not vector or discrete keys "
                f"of the observation space; such keys: {spec.entry_keys}"
            )
        self.entry_labels = {}
        for key in spec.entry_keys:
            names = given.get(key) if isinstance(given, Mapping) else given
            size = int(np.prod(spec.shapes[key]))
            self.entry_labels[key] = observation_labels(key, size, env_id, names)
        if isinstance(self._state_renderer, ClassicControlRenderer):
            self._state_renderer.close()  # a previous learn() call's
        self._state_renderer = None if spec.image_keys else self._make_renderer(env_id)

    def _env_id(self) -> str | None:
        """The gymnasium id of the training env (its first sub-env), or None when it has none."""
        try:
            spec = self.training_env.get_attr("spec", [0])[0]
        except (AttributeError, IndexError):
            return None
        return getattr(spec, "id", None)

    def _make_renderer(self, env_id: str | None) -> Renderer | None:
        if self.renderer is None or callable(self.renderer):
            return self.renderer  # type: ignore[return-value]
        if env_id is None or task_name(env_id) not in CLASSIC_CONTROL_OBSERVATIONS:
            return None
        try:
            renderer = ClassicControlRenderer(env_id)
            renderer.env.render()  # pygame is imported on the first render
        except (gym.error.DependencyNotInstalled, ImportError) as error:
            warnings.warn(
                f"SubgoalDecodeCallback: {env_id} cannot render without pygame ({error}); the pictures show bars "
                "only. pip install pygame (in sb3-hieros[extra]) for the frames",
                UserWarning,
                stacklevel=2,
            )
            return None
        return renderer

    def _draw(self) -> None:
        model = self.model
        snapshot = model.decoded_subgoals()
        if snapshot is None:
            return
        observation, subgoals = snapshot
        spec = model.policy.hierarchy.levels[0].world_model.spec
        keys = list(spec.shapes)
        decoded = [_as_numpy_dict(obs, keys, spec.is_dict) for obs in subgoals]
        real = _as_numpy_dict(observation, keys, spec.is_dict)
        for env in range(self.n_envs_shown):
            frames = None if self._state_renderer is None else [self._frame(obs, env, spec) for obs in [real, *decoded]]
            image = subgoal_picture(
                env,
                spec.image_keys,
                spec.entry_keys,
                real,
                decoded,
                f"step {self.num_timesteps}, env {env}",
                self.entry_labels,
                frames,
            )
            self._write_image(f"subgoals/env{env}", image, f"subgoals_{self.num_timesteps:09d}_env{env}.png")

    def _frame(self, obs: dict[str, np.ndarray], env: int, spec: Any) -> np.ndarray:
        """The renderer's frame of one env's observation, taken back to the env's units under VecNormalize."""
        assert self._state_renderer is not None
        one: Any = {key: value[env].reshape(spec.shapes[key]) for key, value in obs.items()}
        if not spec.is_dict:
            one = one[next(iter(one))]
        normalizer = self.model.get_vec_normalize_env()
        if normalizer is not None:
            one = normalizer.unnormalize_obs(one)
        return np.asarray(self._state_renderer(one), dtype=np.uint8)


class ImaginationCallback(_PeriodicDrawingCallback):
    """Every ``every`` environment steps, show level 0's world model against reality (thesis Fig. 5.1).

    From the newest ``context + horizon`` steps of env 0 in level 0's replay whose last ``horizon`` steps lie in one
    episode (:func:`recent_window`), the world model observes the first ``context`` steps and imagines the next
    ``horizon`` open-loop with the recorded actions (:func:`imagine_open_loop`). The picture shows, per image key,
    the real frames above the model's (reconstructions of the context, then the imagination; a red line marks the
    start of imagination), per vector or discrete key the real and predicted trajectories of the first
    :data:`MAX_PLOTTED_DIMS` entries, and the per-step prediction error of the imagined steps: the mean squared
    error over pixels scaled to [0, 1] (images) or over the entries in observation units (vectors), the share of
    entries that differ (discrete keys: the decoded value is the most likely one). PNGs are
    named ``imagination_<step>.png``, the TensorBoard tag is ``imagination/env0``; the errors are logged as
    ``imagination/<key>error_mean``, ``..._first`` and ``..._last`` (``<key>`` empty for non-Dict spaces) and
    appended to ``save_dir/imagination_errors.csv`` (step, key, then one column per imagined step). Nothing is
    drawn while the replay holds no such window.

    :param every: environment steps between two pictures
    :param horizon: imagined steps (>= 1)
    :param context: observed steps before imagining (>= 1)
    :param save_dir: directory for the PNGs and the CSV, or None
    :param tensorboard: also write to the logger's TensorBoard output
    :param verbose: 0 silent, 1 prints the written files
    """

    def __init__(
        self,
        every: int,
        horizon: int = 15,
        context: int = 5,
        save_dir: SaveDir = None,
        tensorboard: bool = True,
        verbose: int = 0,
    ) -> None:
        super().__init__(every, save_dir, tensorboard, verbose)
        for name, value in (("horizon", horizon), ("context", context)):
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}")
        self.horizon = int(horizon)
        self.context = int(context)
        #: per-step errors of the last drawing: key -> (horizon,) array
        self.last_errors: dict[str, np.ndarray] = {}

    def _draw(self) -> None:
        model = self.model
        buffer: SequenceReplayBuffer = model.replay_buffer
        rows = recent_window(buffer, 0, self.context, self.horizon)
        if rows is None:
            return
        level0 = model.policy.hierarchy.levels[0]
        spec = level0.world_model.spec
        keys = list(spec.shapes)
        chunk = buffer.chunk(0, rows, model.get_vec_normalize_env())  # (1, T, ...), placeholder actions zeroed
        actions = level0.action_vectors(chunk.actions, chunk.is_first)  # (1, T, A)
        obs = chunk.observations
        recon, imagined = imagine_open_loop(level0.world_model, obs, actions, chunk.is_first, self.context)
        recon_np = _as_numpy_dict(recon, keys, spec.is_dict)
        imagined_np = _as_numpy_dict(imagined, keys, spec.is_dict)
        predicted = {key: np.concatenate([recon_np[key], imagined_np[key]], 1)[0] for key in keys}  # (T, *shape)
        real = {key: value[0] for key, value in _as_numpy_dict(obs, keys, spec.is_dict).items()}  # (T, *shape)
        self.last_errors = {}
        for key in keys:
            diff = predicted[key][self.context :] - real[key][self.context :]
            if key in spec.image_keys:
                diff = diff / 255.0
            if key in spec.discrete_keys:  # the share of entries that differ
                diff = (diff != 0).astype(np.float32)
            self.last_errors[key] = np.square(diff.reshape(self.horizon, -1)).mean(1)
        self._log_errors(spec.is_dict)
        image = self._picture(spec.image_keys, spec.entry_keys, real, predicted)
        self._write_image("imagination/env0", image, f"imagination_{self.num_timesteps:09d}.png")

    def _log_errors(self, is_dict: bool) -> None:
        for key, errors in self.last_errors.items():
            prefix = f"imagination/{key}_" if is_dict else "imagination/"
            self.logger.record(f"{prefix}error_mean", float(errors.mean()))
            self.logger.record(f"{prefix}error_first", float(errors[0]))
            self.logger.record(f"{prefix}error_last", float(errors[-1]))
        if self.save_dir is not None:
            path = self.save_dir / "imagination_errors.csv"
            new = not path.exists()
            with path.open("a") as handle:
                if new:
                    steps = ",".join(f"error_t{t}" for t in range(1, self.horizon + 1))
                    handle.write(f"num_timesteps,key,{steps}\n")
                for key, errors in self.last_errors.items():
                    values = ",".join(f"{e:.6g}" for e in errors)
                    handle.write(f"{self.num_timesteps},{key},{values}\n")

    def _picture(
        self,
        image_keys: list[str],
        vector_keys: list[str],
        real: dict[str, np.ndarray],
        predicted: dict[str, np.ndarray],
    ) -> np.ndarray:
        """Strips of real and predicted frames per image key, trajectories per vector or discrete key, and the error
        curve."""
        context, length = self.context, self.context + self.horizon
        vector_panels = [(key, d) for key in vector_keys for d in range(min(real[key][0].size, MAX_PLOTTED_DIMS))]
        vector_rows = (len(vector_panels) + 3) // 4
        width = float(np.clip(0.6 * length, 9.0, 16.0))
        heights = []
        for key in image_keys:
            _, height, frame_width = real[key].shape[-3:]
            strip_aspect = length * (frame_width + 1) / height
            heights += [max(width * 0.9 / strip_aspect, 0.6)] * 2  # real and model strip
        heights += [2.0] * vector_rows + [2.2]
        figure = new_figure(width, sum(heights) + 0.8)
        grid = figure.add_gridspec(len(heights), 4, height_ratios=heights)
        row = 0
        for key in image_keys:
            for source, label in ((real, "real"), (predicted, "model")):
                frames = [display_image(frame) for frame in source[key]]
                height, width = frames[0].shape[:2]
                gap = np.full((height, 1, 3), 255, np.uint8)
                strip = np.concatenate([part for frame in frames for part in (frame, gap)][:-1], 1)
                ax = figure.add_subplot(grid[row, :])
                ax.imshow(strip, interpolation="nearest", aspect="equal")
                ax.axvline(context * (width + 1) - 1, color="red", linewidth=2)
                ax.set_xticks([])
                ax.set_yticks([])
                ax.set_ylabel(label if len(image_keys) == 1 else f"{label}\n[{key}]", fontsize=9)
                row += 1
        t = np.arange(length)
        for index, (key, d) in enumerate(vector_panels):
            ax = figure.add_subplot(grid[row + index // 4, index % 4])
            ax.plot(t, real[key].reshape(length, -1)[:, d], "o-", color="black", markersize=3, label="real")
            ax.plot(t, predicted[key].reshape(length, -1)[:, d], "s--", markersize=3, label="model")
            ax.axvline(context - 0.5, color="red", linewidth=1)
            ax.set_title(f"entry {d}" if key == "obs" else f"{key}[{d}]", fontsize=9)
            ax.tick_params(labelsize=7)
            if index == 0:
                ax.legend(fontsize=7)
        row += vector_rows
        ax = figure.add_subplot(grid[row, :])
        steps = np.arange(1, self.horizon + 1)
        for key, errors in self.last_errors.items():
            ax.plot(steps, errors, "o-", label=key if len(self.last_errors) > 1 else None)
        ax.set_xlabel("imagined step")
        ax.set_ylabel("mean squared error")
        ax.grid(alpha=0.3)
        if len(self.last_errors) > 1:
            ax.legend(fontsize=8)
        figure.suptitle(
            f"world model vs reality, step {self.num_timesteps}: {context} observed steps, then {self.horizon} "
            "imagined open-loop (right of the red line)",
            fontsize=10,
        )
        figure.tight_layout()
        return figure_pixels(figure)
