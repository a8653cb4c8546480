"""sb3-hieros: the HIEROS agent for Stable-Baselines3."""

__version__ = "0.1.0"

__all__ = ["__version__"]
