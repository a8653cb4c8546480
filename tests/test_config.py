import dataclasses

import pytest

from sb3_hieros.config import HierosConfig, WorldModelConfig, get_preset


def test_paper_preset_matches_thesis_table():
    cfg = get_preset("paper")
    wm, ac, sg = cfg.world_model, cfg.actor_critic, cfg.subgoal
    assert (cfg.batch_size, cfg.batch_length, cfg.imag_horizon) == (16, 64, 16)
    assert (cfg.n_levels, cfg.subgoal_interval, cfg.etbs_temperature) == (3, 4, 0.3)
    assert (ac.extrinsic_weight, ac.subgoal_weight, ac.novelty_weight) == (1.0, 0.3, 0.1)
    assert (sg.n_cat, sg.n_classes, sg.beta) == (8, 8, 0.5)
    assert (wm.s5_model_dim, wm.s5_state_dim, wm.s5_hippo_blocks, wm.s5_layers) == (256, 128, 4, 8)
    assert (wm.dyn_scale, wm.rep_scale, wm.deter_dim) == (0.5, 0.1, 256)
    assert (wm.stoch_groups, wm.stoch_classes, wm.lr, wm.weight_decay) == (32, 32, 1e-4, 0.0)
    assert not cfg.replay_context  # the thesis trains every chunk from zeros


def test_small_preset_is_smaller_everywhere():
    paper, small = get_preset("paper"), get_preset("small")
    assert small.world_model.s5_layers < paper.world_model.s5_layers
    assert small.world_model.deter_dim < paper.world_model.deter_dim
    assert small.train_ratio < paper.train_ratio
    assert small.replay_context  # the CPU preset trains from the replay context


def test_presets_are_fresh_copies():
    a = get_preset("paper")
    a.world_model.s5_layers = 1
    assert get_preset("paper").world_model.s5_layers == 8


def test_replace_nested_and_validates():
    cfg = get_preset("paper").replace(n_levels=2, world_model={"s5_layers": 4})
    assert cfg.n_levels == 2 and cfg.world_model.s5_layers == 4
    assert cfg.world_model.s5_model_dim == 256
    with pytest.raises(ValueError, match="bogus"):
        cfg.replace(bogus=1)
    with pytest.raises(ValueError, match="s5_layer"):
        cfg.replace(world_model={"s5_layer": 4})
    with pytest.raises(ValueError, match="n_levels"):
        cfg.replace(n_levels=0)


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"kind": "lstm"}, "kind"),
        ({"deter_from": "both"}, "deter_from"),
        ({"action_input": "split"}, r"action_input must be one of \('joint', 'separate'\), got 'split'"),
        ({"posterior": "both"}, r"posterior must be one of \('auto', 'observation', 'state'\), got 'both'"),
        ({"s5_state_dim": 100, "s5_hippo_blocks": 3}, "divisible"),
        ({"dropout": 1.5}, "dropout"),
        ({"lr": -1.0}, "lr"),
    ],
)
def test_world_model_config_rejects_bad_values(changes, match):
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(WorldModelConfig(), **changes)


def test_unknown_preset():
    with pytest.raises(ValueError, match="tiny"):
        get_preset("tiny")


def test_hieros_config_rejects_bad_replay():
    with pytest.raises(ValueError, match="replay"):
        HierosConfig(replay="prioritized")
    with pytest.raises(ValueError, match=r"HierosConfig\.replay_context must be a bool, got 1"):
        HierosConfig(replay_context=1)


def test_hieros_config_rejects_bad_world_model_updates():
    with pytest.raises(ValueError, match="world_model_updates"):
        HierosConfig(world_model_updates=0)
    assert HierosConfig(world_model_updates=4).world_model_updates == 4


def test_learning_starts_are_checked():
    assert HierosConfig().actor_learning_starts == 0 and get_preset("small").actor_learning_starts == 0
    assert HierosConfig(actor_learning_starts=3000).actor_learning_starts == 3000
    with pytest.raises(ValueError, match=r"HierosConfig\.learning_starts must be a number >= 0, got -1"):
        HierosConfig(learning_starts=-1)
    with pytest.raises(ValueError, match=r"HierosConfig\.actor_learning_starts must be a number >= 0, got -5"):
        HierosConfig(actor_learning_starts=-5)
    with pytest.raises(ValueError, match=r"HierosConfig\.actor_learning_starts must be an integer, got 2000\.0"):
        HierosConfig(actor_learning_starts=2000.0)


def test_replay_value_loss_is_checked():
    small = get_preset("small")
    assert small.actor_critic.replay_value_loss == 0.0
    assert small.replace(actor_critic={"replay_value_loss": 0.3}).actor_critic.replay_value_loss == 0.3
    with pytest.raises(ValueError, match=r"ActorCriticConfig\.replay_value_loss must be >= 0, got -0\.3"):
        small.replace(actor_critic={"replay_value_loss": -0.3})
    with pytest.raises(ValueError, match=r"replay_value_loss=0\.3 needs hierarchical_world_models=True"):
        small.replace(actor_critic={"replay_value_loss": 0.3}, hierarchical_world_models=False)


def test_world_model_lr_zero_is_a_frozen_model_and_negative_is_refused():
    assert get_preset("small").replace(world_model={"lr": 0.0}).world_model.lr == 0.0
    with pytest.raises(ValueError, match=r"WorldModelConfig\.lr must be a number >= 0, got -0\.001"):
        get_preset("small").replace(world_model={"lr": -1e-3})


def test_return_critic_is_checked():
    small = get_preset("small")
    assert small.actor_critic.return_critic == "fast"
    assert small.replace(actor_critic={"return_critic": "slow"}).actor_critic.return_critic == "slow"
    with pytest.raises(ValueError, match=r"return_critic.*'target'"):
        small.replace(actor_critic={"return_critic": "target"})
