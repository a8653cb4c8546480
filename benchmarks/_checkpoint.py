"""Periodic checkpoints of a HIEROS run, shared by :mod:`benchmarks.train` and :mod:`benchmarks.soak`.

A checkpoint is a model zip and a replay file named by the step (:func:`checkpoint_paths`), saved at the start of a
vec-env step: then the previous step's transition is stored and its updates are made, so a run resumed from it lacks
nothing (``docs/resume.md``).
"""

from __future__ import annotations

import pathlib
from typing import Any

from stable_baselines3.common.callbacks import BaseCallback

__all__ = ["PeriodicCheckpoint", "check_same_options", "checkpoint_paths", "checkpoint_steps", "load_checkpoint"]


def checkpoint_paths(directory: pathlib.Path, step: int) -> tuple[pathlib.Path, pathlib.Path]:
    """The model and replay files of the checkpoint at ``step``."""
    return directory / f"model_{step}.zip", directory / f"replay_{step}.zip"


def checkpoint_steps(directory: pathlib.Path) -> list[int]:
    """Steps of the checkpoints whose model and replay files both exist, newest first."""
    steps = {int(p.stem.split("_")[1]) for p in directory.glob("model_*.zip")}
    return sorted((s for s in steps if checkpoint_paths(directory, s)[1].exists()), reverse=True)


def load_checkpoint(directory: pathlib.Path, step: int, env: Any, **load_kwargs: Any) -> Any:
    """The HIEROS model of the checkpoint at ``step`` on ``env``, with its replay (every level) loaded.

    :param directory: the checkpoint folder
    :param step: the checkpoint's step (:func:`checkpoint_steps`)
    :param env: the env the model goes on with
    :param load_kwargs: passed to ``HIEROS.load`` (e.g. ``device``, ``safe``)
    :return: the model
    """
    from sb3_hieros import HIEROS

    model_path, replay_path = checkpoint_paths(directory, step)
    model = HIEROS.load(model_path, env=env, **load_kwargs)
    model.load_replay_buffer(replay_path)
    return model


def check_same_options(saved: dict[str, Any], options: dict[str, Any], path: pathlib.Path) -> None:
    """Refuse to resume from ``path`` (a checkpoint's progress or a finished run's record) when one of the run's
    options that it holds differs from ``options``, naming each.

    :param saved: the options (or the record) read from ``path``
    :param options: the options of this call
    :param path: the file they were read from, for the message
    """
    changed = sorted(k for k in options if k in saved and saved[k] != options[k])
    if changed:
        raise ValueError(
            f"{path} belongs to a run with other options: "
            + ", ".join(f"{k} {saved[k]!r} (now {options[k]!r})" for k in changed)
            + "; resume with the same options, or remove the run's folder to start afresh"
        )


class PeriodicCheckpoint(BaseCallback):
    """Saves the model and its replay (every level) into ``directory`` at the start of every ``every``-th vec-env
    step, once per step count: not at the step a run starts or resumes from. Subclasses extend :meth:`_save`.

    :param directory: the checkpoint folder (created on the first save)
    :param every: steps between checkpoints
    """

    def __init__(self, directory: pathlib.Path, every: int) -> None:
        super().__init__()
        self.directory = directory
        self.every = every
        self.last_saved = -1

    def _on_training_start(self) -> None:
        self.last_saved = self.model.num_timesteps  # the checkpoint resumed from (or nothing to save at step 0)

    def _on_rollout_start(self) -> None:
        step = self.model.num_timesteps
        if step % self.every or step == self.last_saved:
            return
        self._save(step)
        self.last_saved = step

    def _save(self, step: int) -> None:
        """Write the model and replay files of the checkpoint at ``step`` (:func:`checkpoint_paths`)."""
        self.directory.mkdir(parents=True, exist_ok=True)
        model_path, replay_path = checkpoint_paths(self.directory, step)
        self.model.save(model_path)
        self.model.save_replay_buffer(replay_path)  # type: ignore[attr-defined]

    def _on_step(self) -> bool:
        return True
