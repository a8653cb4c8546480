"""Warnings a new user meets: a run that ends before the first update, and the paper preset built on a CPU."""

from __future__ import annotations

import re
import warnings

import gymnasium as gym
import pytest
from hieros_helpers import tiny_kwargs

from sb3_hieros import HIEROS


def _user_warnings(record: list[warnings.WarningMessage]) -> list[str]:
    return [str(w.message) for w in record if issubclass(w.category, UserWarning)]


def test_learn_warns_when_it_ends_before_the_first_update():
    model = HIEROS("MlpPolicy", gym.make("CartPole-v1"), **tiny_kwargs(learning_starts=20))
    with pytest.warns(UserWarning, match=r"learn\(10\) ends at 10 environment steps, before the first update") as rec:
        model.learn(10)
    assert rec[0].filename == __file__  # points at the caller's line
    assert "learning_starts=20" in str(rec[0].message) and "more than 20 steps" in str(rec[0].message)
    assert model._level_updates == [0, 0]  # it really trained nothing

    # continuing a run counts the steps already done: 10 + 10 = 20 still does not pass learning_starts
    with pytest.warns(UserWarning, match=r"ends at 20 environment steps.*more than 10 steps"):
        model.learn(10, reset_num_timesteps=False)
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        model.learn(12, reset_num_timesteps=False)  # ends at 32 > 20: trains
    assert not [m for m in _user_warnings(record) if "before the first update" in m]
    assert model._level_updates[0] > 0

    # a fresh run of more than learning_starts steps says nothing
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        model.learn(21)
    assert not [m for m in _user_warnings(record) if "before the first update" in m]


def test_paper_preset_on_a_cpu_warns_with_its_size(tmp_path):
    # preset left out: the paper preset (one level and a short replay to keep the test cheap)
    with pytest.warns(UserWarning, match="'paper' preset") as record:
        model = HIEROS("MlpPolicy", "CartPole-v1", config_overrides={"n_levels": 1}, buffer_size=1_000, device="cpu")
    # the preset's warning, whatever else torch warned about on the way
    (paper,) = [w for w in record if "'paper' preset" in str(w.message)]
    message = str(paper.message)
    assert paper.filename == __file__
    n_params = sum(p.numel() for p in model.policy.parameters())
    assert f"{n_params / 1e6:.1f}M parameters" in message
    assert re.search(r'pass preset="small"', message)
    model.save(tmp_path / "paper")
    # the CPU preset and a loaded paper model stay silent
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        HIEROS(
            "MlpPolicy",
            "CartPole-v1",
            preset="small",
            config_overrides={"n_levels": 1},
            buffer_size=1_000,
            device="cpu",
        )
        HIEROS.load(tmp_path / "paper", device="cpu")
    assert not [m for m in _user_warnings(record) if "'paper' preset" in m]
