"""Adapters that give a vecsim job the env contract of an RL trainer (docs/trainers.md)."""
