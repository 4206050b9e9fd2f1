"""Rendering: pybullet scenes from maze specs (online) and the offline render cache."""
