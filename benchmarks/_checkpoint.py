"""Periodic checkpoints of a HIEROS run, shared by :mod:`benchmarks.train` and :mod:`benchmarks.soak`.

A checkpoint is a model zip and a replay file named by the step (:func:`checkpoint_paths`), saved at the start of a
vec-env step: then the previous step's transition is stored and its updates are made, so a run resumed from it lacks
nothing (``docs/resume.md``).
"""

from __future__ import annotations

import pathlib

from stable_baselines3.common.callbacks import BaseCallback

__all__ = ["PeriodicCheckpoint", "checkpoint_paths", "checkpoint_steps"]


def checkpoint_paths(directory: pathlib.Path, step: int) -> tuple[pathlib.Path, pathlib.Path]:
    """The model and replay files of the checkpoint at ``step``."""
    return directory / f"model_{step}.zip", directory / f"replay_{step}.zip"


def checkpoint_steps(directory: pathlib.Path) -> list[int]:
    """Steps of the checkpoints whose model and replay files both exist, newest first."""
    steps = {int(p.stem.split("_")[1]) for p in directory.glob("model_*.zip")}
    return sorted((s for s in steps if checkpoint_paths(directory, s)[1].exists()), reverse=True)


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
