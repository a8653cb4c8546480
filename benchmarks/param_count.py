"""Parameter count of the ``paper`` preset for Atari, per level and component, next to the thesis' 37.1M.

``python -m benchmarks.param_count`` builds the three levels of thesis table 4.6.3 for a 3x64x64 uint8 image and 18
actions: level 0 sees the image and acts in the env; levels 1 and 2 see k = 4 stacked world states ``[h, z]`` of the
level below and act in its 8 x 8 subgoal space; level 2 is the top level (no subgoal input, no subgoal critic).

Two counting conventions are printed:

* ``real``: every real number that is trained or stored as a parameter (complex S5 parameters as two reals, slow
  critics included).
* ``complex once``: the reference implementation's own counter, which counts a
  complex parameter as one: our S5 layers store ``Lambda`` as (log(-Re), Im) and ``C`` as (real, imaginary) pairs, so
  P + H*P per S5 layer is subtracted (``B`` is stored as real pairs in both implementations and counted as two).
  Slow critics are included, as in the reference's count.

The thesis' 37.1M (= the reference's 37,128,487) was counted with the novelty reward on the higher levels only
(``novelty_only_higher_level``), so the last lines also give the total with level 0 built without a novelty critic.
The last lines print ``name: value``.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_hieros.agent.subactor import Subactor
from sb3_hieros.config import HierosConfig, get_preset
from sb3_hieros.nn.s5 import S5Layer

THESIS_TOTAL = 37.1e6
REFERENCE_TOTAL = 37_128_487
COMPONENTS = (
    "world_model/encoder",
    "world_model/sequence_model",
    "world_model/heads",
    "world_model/decoder",
    "actor",
    "critics",
    "slow_critics",
    "subgoal_autoencoder",
)


def complex_duplicates(sub: Subactor) -> int:
    """Reals that the reference's counter would not count: one per complex S5 parameter entry (Lambda, C).

    :param sub: a level
    :return: number of parameters to subtract for the "complex once" convention
    """
    extra = 0
    for module in sub.modules():
        if isinstance(module, S5Layer):
            extra += module.lambda_imag.numel() + module.C.numel() // 2
    return extra


def build_levels(config: HierosConfig, image_shape: tuple[int, int, int], n_actions: int) -> list[Subactor]:
    """The ``n_levels`` levels of HIEROS for an image env with a Discrete action space.

    :param config: hyperparameters
    :param image_shape: (C, H, W)
    :param n_actions: number of env actions
    :return: levels, bottom first
    """
    obs_space: spaces.Space = spaces.Box(0, 255, image_shape, np.uint8)
    action_space: spaces.Space = spaces.Discrete(n_actions)
    levels = []
    for i in range(config.n_levels):
        top = i == config.n_levels - 1
        sub = Subactor(obs_space, action_space, config, level=i, subgoal_input=not top)
        levels.append(sub)
        obs_space = sub.higher_level_observation_space(config.subgoal_interval)
        action_space = sub.subgoal_space()
    return levels


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="paper", help="config preset (default: paper)")
    parser.add_argument("--actions", type=int, default=18, help="number of env actions (default: 18, full Atari)")
    parser.add_argument("--image", type=int, nargs=3, default=(3, 64, 64), help="image shape C H W")
    args = parser.parse_args(argv)

    th.manual_seed(0)
    config = get_preset(args.preset)
    levels = build_levels(config, tuple(args.image), args.actions)
    counts = [sub.parameter_counts() for sub in levels]
    dup = [complex_duplicates(sub) for sub in levels]

    print(f"preset {args.preset!r}: {config.n_levels} levels, image {tuple(args.image)} uint8, {args.actions} actions")
    for i, sub in enumerate(levels):
        print(
            f"  level {i}: obs {sub.observation_space.shape}, actions {sub.action_space}, "
            f"reward terms {sub.reward_terms}, actor input {sub.feat_dim}"
        )
    header = f"{'component':28s}" + "".join(f"{f'level {i}':>14s}" for i in range(len(levels))) + f"{'all':>14s}"
    print(header)
    for name in COMPONENTS:
        row = [c[name] for c in counts]
        print(f"{name:28s}" + "".join(f"{v:14,d}" for v in row) + f"{sum(row):14,d}")
    totals = [c["total"] for c in counts]
    once = [t - d for t, d in zip(totals, dup, strict=True)]
    slow = [c["slow_critics"] for c in counts]
    print(f"{'total (real)':28s}" + "".join(f"{v:14,d}" for v in totals) + f"{sum(totals):14,d}")
    print(f"{'total (complex once)':28s}" + "".join(f"{v:14,d}" for v in once) + f"{sum(once):14,d}")

    level0_no_novelty = Subactor(
        levels[0].observation_space, levels[0].action_space, config.replace(actor_critic={"novelty_weight": 0.0})
    )
    ref_novelty_total = sum(once) - once[0] + level0_no_novelty.parameter_counts()["total"] - dup[0]

    for i, (t, o) in enumerate(zip(totals, once, strict=True)):
        print(f"level{i}_total_real: {t}")
        print(f"level{i}_total_complex_once: {o}")
    print(f"total_real: {sum(totals)}")
    print(f"total_complex_once: {sum(once)}")
    print(f"total_complex_once_without_slow_critics: {sum(once) - sum(slow)}")
    print(f"total_complex_once_novelty_only_higher_levels: {ref_novelty_total}")
    print(f"reference_code_count: {REFERENCE_TOTAL}")
    print(f"thesis_total: {THESIS_TOTAL:.3g}")


if __name__ == "__main__":
    main()
