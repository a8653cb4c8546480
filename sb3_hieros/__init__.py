"""sb3-hieros: the HIEROS agent for Stable-Baselines3."""

from sb3_hieros.buffers import DictSequenceReplayBuffer, ETBSReplayBuffer, SequenceReplayBuffer
from sb3_hieros.callbacks import ImaginationCallback, SubgoalDecodeCallback
from sb3_hieros.config import HierosConfig, get_preset
from sb3_hieros.hieros import HIEROS
from sb3_hieros.policies import CnnPolicy, HierosPolicy, MlpPolicy, MultiInputPolicy

__version__ = "0.1.0"

__all__ = [
    "HIEROS",
    "CnnPolicy",
    "DictSequenceReplayBuffer",
    "ETBSReplayBuffer",
    "HierosConfig",
    "HierosPolicy",
    "ImaginationCallback",
    "MlpPolicy",
    "MultiInputPolicy",
    "SequenceReplayBuffer",
    "SubgoalDecodeCallback",
    "__version__",
    "get_preset",
]
