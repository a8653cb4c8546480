"""Drawing observations for the callbacks (:mod:`sb3_hieros.callbacks`): what the entries of the vector observations
of gymnasium's classic-control tasks mean, a renderer that draws such an observation as the task's frame, and the
matplotlib helpers (an Agg figure without pyplot, channel-first images as RGB).
"""

from __future__ import annotations

import os
import textwrap
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

__all__ = [
    "CLASSIC_CONTROL_OBSERVATIONS",
    "ClassicControlRenderer",
    "ObservationLayout",
    "Renderer",
    "display_image",
    "figure_pixels",
    "new_figure",
    "observation_labels",
    "require_matplotlib",
    "subgoal_picture",
    "task_name",
]

#: A function that draws one observation (as the env gives it, a dict of arrays for Dict spaces) as an RGB frame
#: (H, W, 3) uint8.
Renderer = Callable[[Any], np.ndarray]

# ----------------------------------------------------------------------------------------------------------------------
# What the entries of a vector observation mean (gymnasium's classic-control tasks)
# ----------------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ObservationLayout:
    """The entries of a task's observation vector and how to turn an observation into the ``env.unwrapped.state``
    that the task's ``render()`` draws.

    :param labels: name of every entry of the observation vector
    :param state_from_obs: observation (D,) -> the env's ``state`` array
    """

    labels: tuple[str, ...]
    state_from_obs: Callable[[np.ndarray], np.ndarray]


def _same(obs: np.ndarray) -> np.ndarray:
    return obs


def _pendulum_state(obs: np.ndarray) -> np.ndarray:
    return np.array([np.arctan2(obs[1], obs[0]), obs[2]])  # (cos, sin, velocity) -> (angle, velocity)


def _acrobot_state(obs: np.ndarray) -> np.ndarray:
    return np.array([np.arctan2(obs[1], obs[0]), np.arctan2(obs[3], obs[2]), obs[4], obs[5]])


#: gymnasium classic-control task name (the id without version) -> the layout of its observation vector.
CLASSIC_CONTROL_OBSERVATIONS: dict[str, ObservationLayout] = {
    "CartPole": ObservationLayout(("cart position", "cart velocity", "pole angle", "pole angular velocity"), _same),
    "MountainCar": ObservationLayout(("car position", "car velocity"), _same),
    "MountainCarContinuous": ObservationLayout(("car position", "car velocity"), _same),
    "Pendulum": ObservationLayout(("cos(angle)", "sin(angle)", "angular velocity"), _pendulum_state),
    "Acrobot": ObservationLayout(
        ("cos(joint 1)", "sin(joint 1)", "cos(joint 2)", "sin(joint 2)", "joint 1 velocity", "joint 2 velocity"),
        _acrobot_state,
    ),
}


def task_name(env_id: str) -> str:
    """``"CartPole-v1"`` -> ``"CartPole"`` (namespace and version dropped; an id gymnasium cannot parse as it is)."""
    try:
        return gym.envs.registration.parse_env_id(env_id)[1]
    except gym.error.Error:
        return env_id


def observation_labels(
    key: str, size: int, env_id: str | None = None, labels: Sequence[str] | None = None
) -> list[str]:
    """Names of the ``size`` entries of a vector observation: ``labels`` if given, else those of a classic-control
    task (:data:`CLASSIC_CONTROL_OBSERVATIONS`) of the right size, else ``obs[i]`` (``<key>[i]`` in Dict spaces).

    :param key: the observation key (``"obs"`` for non-Dict spaces)
    :param size: number of entries
    :param env_id: gymnasium id of the env, or None
    :param labels: names given by the user, or None
    :return: one name per entry
    """
    if labels is not None:
        if isinstance(labels, str) or len(labels) != size:
            raise ValueError(f"labels for observation {key!r} must name its {size} entries, got {labels!r}")
        return [str(label) for label in labels]
    layout = CLASSIC_CONTROL_OBSERVATIONS.get(task_name(env_id)) if env_id else None
    if key == "obs" and layout is not None and len(layout.labels) == size:
        return list(layout.labels)
    return [f"{key}[{i}]" for i in range(size)]


class ClassicControlRenderer:
    """Draws an observation of a gymnasium classic-control task as the frame the task renders for that state: sets
    ``env.unwrapped.state`` of an ``rgb_array`` env of the same id and calls ``render()`` (needs pygame).

    On a machine without a display (neither ``DISPLAY`` nor ``WAYLAND_DISPLAY`` set) it sets ``SDL_VIDEODRIVER=dummy``
    unless the variable is already set: the frames are drawn off-screen, and SDL would otherwise print an error
    about the missing display.

    :param env_id: gymnasium id of a task in :data:`CLASSIC_CONTROL_OBSERVATIONS`, e.g. ``"CartPole-v1"``
    """

    def __init__(self, env_id: str) -> None:
        name = task_name(env_id) if isinstance(env_id, str) else None
        if name not in CLASSIC_CONTROL_OBSERVATIONS:
            raise ValueError(
                f"env_id must be a classic-control task, one of {sorted(CLASSIC_CONTROL_OBSERVATIONS)}, got {env_id!r}"
            )
        self.layout = CLASSIC_CONTROL_OBSERVATIONS[name]
        if "DISPLAY" not in os.environ and "WAYLAND_DISPLAY" not in os.environ:
            os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        self.env = gym.make(env_id, render_mode="rgb_array")
        self.env.reset(seed=0)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The frame of one observation.

        :param obs: observation (D,) in the env's units
        :return: (H, W, 3) uint8 frame
        """
        vector = np.asarray(obs, dtype=np.float64).reshape(-1)
        if vector.size != len(self.layout.labels):
            raise ValueError(f"expected an observation of {len(self.layout.labels)} entries, got shape {np.shape(obs)}")
        self.env.unwrapped.state = self.layout.state_from_obs(vector)  # type: ignore[attr-defined]
        return np.asarray(self.env.render(), dtype=np.uint8)

    def close(self) -> None:
        """Close the env used for drawing."""
        self.env.close()


# ----------------------------------------------------------------------------------------------------------------------
# Rendering helpers
# ----------------------------------------------------------------------------------------------------------------------


def require_matplotlib() -> None:
    try:
        import matplotlib  # noqa: F401
    except ImportError as error:  # pragma: no cover - depends on the installation
        raise ImportError(
            "the sb3_hieros callbacks draw with matplotlib: pip install 'sb3-hieros[extra]' or pip install matplotlib"
        ) from error


def new_figure(width: float, height: float) -> Any:
    """A matplotlib Figure with an Agg canvas (no pyplot, no global backend change)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(width, height), dpi=100)
    FigureCanvasAgg(figure)
    return figure


def figure_pixels(figure: Any) -> np.ndarray:
    """The figure as an (H, W, 3) uint8 RGB array."""
    figure.canvas.draw()
    return np.asarray(figure.canvas.buffer_rgba())[..., :3].copy()


def display_image(image: np.ndarray) -> np.ndarray:
    """A channel-first image (C, H, W) in [0, 255] as (H, W, 3) uint8: grey for one channel, RGB for three; for
    stacked frames (C a multiple of 3: the last 3 channels, otherwise the last channel)."""
    pixels = np.clip(np.asarray(image, dtype=np.float32), 0.0, 255.0).round().astype(np.uint8)
    channels = pixels.shape[0]
    if channels == 3:
        chosen = pixels
    elif channels % 3 == 0:
        chosen = pixels[-3:]
    else:
        chosen = np.repeat(pixels[-1:], 3, 0)
    return np.ascontiguousarray(chosen.transpose(1, 2, 0))


def subgoal_picture(
    env: int,
    image_keys: list[str],
    vector_keys: list[str],
    real: dict[str, np.ndarray],
    decoded: list[dict[str, np.ndarray]],
    title: str,
    entry_labels: Mapping[str, Sequence[str]] | None = None,
    frames: list[np.ndarray] | None = None,
) -> np.ndarray:
    """One env's picture of :class:`~sb3_hieros.callbacks.SubgoalDecodeCallback`: a row of images per image key, a
    bar chart per vector or discrete key, a row of rendered frames.

    :param env: index of the env
    :param image_keys: keys of the image entries
    :param vector_keys: keys of the vector and discrete entries
    :param real: key -> (n_envs, ...) real observation
    :param decoded: per level above 0, key -> (n_envs, ...) decoded subgoal
    :param title: title suffix
    :param entry_labels: key -> names of their entries (default ``obs[i]`` / ``<key>[i]``)
    :param frames: rendered frames of the real observation and of every decoded subgoal, or None
    :return: (H, W, 3) uint8 picture
    """
    columns = 1 + len(decoded)
    names = ["observation"] + [f"level-{i} subgoal" for i in range(1, columns)]
    widest = max([real[key][env].size for key in vector_keys], default=0)
    figure_width = min(max(2.2 * columns, 4.5, 0.9 * widest * (1 + 0.25 * columns)), 16.0)
    heights = [2.4] * len(image_keys) + [2.8] * len(vector_keys)
    if frames is not None:  # one frame per column at the frame's aspect ratio, plus its title
        height, width = frames[0].shape[:2]
        heights.append(min(0.9 * figure_width / columns * height / width, 3.5) + 0.3)
    figure = new_figure(figure_width, sum(heights) + 0.5)
    grid = figure.add_gridspec(len(heights), columns, height_ratios=heights)
    for row, key in enumerate(image_keys):
        panels = [real[key][env]] + [d[key][env] for d in decoded]
        for col, (panel, label) in enumerate(zip(panels, names, strict=True)):
            ax = figure.add_subplot(grid[row, col])
            ax.imshow(display_image(panel), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(label if len(image_keys) == 1 else f"{label}\n[{key}]", fontsize=9)
    for offset, key in enumerate(vector_keys):
        ax = figure.add_subplot(grid[len(image_keys) + offset, :])
        values = [real[key][env].reshape(-1)] + [d[key][env].reshape(-1) for d in decoded]
        x = np.arange(values[0].size)
        bar = 0.8 / columns  # bar width: one group of bars per entry
        for i, (value, name) in enumerate(zip(values, names, strict=True)):
            color = "black" if i == 0 else f"C{i - 1}"
            label = name if i == 0 else f"{name} (decoded)"
            ax.bar(x + (i - (columns - 1) / 2) * bar, value, bar, color=color, alpha=0.85, label=label)
        labels = (entry_labels or {}).get(key) or [f"{key}[{i}]" for i in range(x.size)]
        labels = [textwrap.fill(label, 14) for label in labels]  # long names on two lines
        ax.set_xticks(x, labels, rotation=0 if x.size <= 6 else 45, ha="center" if x.size <= 6 else "right")
        ax.axhline(0.0, color="grey", linewidth=0.8)
        ax.set_ylabel("value" if key == "obs" else f"{key!r} value")
        ax.grid(alpha=0.3, axis="y")
        ax.legend(fontsize=8, loc="best")
    if frames is not None:
        for col, (frame, name) in enumerate(zip(frames, names, strict=True)):
            ax = figure.add_subplot(grid[len(heights) - 1, col])
            ax.imshow(frame)
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(name if col == 0 else f"{name} (decoded)", fontsize=9)
    figure.suptitle(f"decoded subgoals, {title}", fontsize=10)
    figure.tight_layout()
    return figure_pixels(figure)
