"""benchmarks/continuation.py: a saved run continues with its world models frozen or learning."""

from __future__ import annotations

import pytest
import torch as th
from hieros_helpers import tiny_kwargs

from benchmarks.continuation import continue_run, main
from benchmarks.train import run_dir, train
from sb3_hieros import HIEROS


@pytest.fixture(scope="module")
def saved_run(tmp_path_factory):
    kwargs = tiny_kwargs()
    overrides = kwargs.pop("config_overrides")
    for name in ("preset", "seed"):
        kwargs.pop(name)
    out = tmp_path_factory.mktemp("runs")
    train(
        "classic", "Pendulum-v1", preset="small", steps=60, eval_freq=0, eval_episodes=1, out=out,
        config_overrides=overrides, hieros_kwargs=kwargs, save_replay_buffer=True,
    )  # fmt: skip
    return run_dir(out, "classic", "Pendulum-v1", 0)


def _parts(model: HIEROS) -> tuple[dict[str, th.Tensor], dict[str, th.Tensor]]:
    level = model.policy.hierarchy.levels[0]
    world_model = {k: v.clone() for k, v in level.world_model.state_dict().items()}
    actor = {k: v.clone() for k, v in level.state_dict().items() if "actor" in k and "world_model" not in k}
    return world_model, actor


def _changed(before: dict[str, th.Tensor], after: dict[str, th.Tensor]) -> bool:
    return any(not th.equal(before[k], after[k]) for k in before)


@pytest.mark.parametrize("freeze", [True, False])
def test_continuation_freezes_only_the_world_models(saved_run, tmp_path, freeze):
    world_model, actor = _parts(HIEROS.load(saved_run / "model.zip"))
    assert actor, "no actor parameters found"
    figures = continue_run(
        saved_run, "classic", "Pendulum-v1", steps=20, train_ratio=8.0, freeze_world_model=freeze, eval_every=10,
        eval_episodes=1, save=tmp_path / "continued.zip",
    )  # fmt: skip
    expected = {"return_at_0", "return_at_10", "return_at_20", "return_std_at_20", "value_at_20", "level0_updates"}
    assert expected <= set(figures)
    assert figures["return_at_0"] < figures["discounted_return_at_0"] < 0  # Pendulum: rewards <= 0, discounted
    assert figures["level0_updates"] == 20 * 8.0 / (2 * 8)  # batch 2 x length 8 per update
    new_world_model, new_actor = _parts(HIEROS.load(tmp_path / "continued.zip"))
    assert _changed(actor, new_actor)
    assert _changed(world_model, new_world_model) is not freeze


def test_continuation_refuses_a_run_without_replay(saved_run, tmp_path):
    (tmp_path / "model.zip").write_bytes((saved_run / "model.zip").read_bytes())
    with pytest.raises(ValueError, match=r"has no replay_buffer\.pkl"):
        main(["--run", str(tmp_path), "--suite", "classic", "--task", "Pendulum-v1"])
    with pytest.raises(ValueError, match="eval_every must be an int >= 1, got 0"):
        continue_run(saved_run, "classic", "Pendulum-v1", eval_every=0)
