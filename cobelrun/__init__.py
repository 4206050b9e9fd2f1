"""cobel: config-driven experiment runner for neuroscience-oriented reinforcement learning."""

__version__ = "0.1.0"
