"""vecsim: robot simulation served over HTTP to RL trainers."""

__version__ = "0.1.0"
