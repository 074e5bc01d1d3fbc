"""bulbjax: the bulb evaluation suite for unsupervised representation learning, on MJX."""

from bulbjax.envs import env_names, make

__all__ = ["make", "env_names"]
__version__ = "0.1.0"
