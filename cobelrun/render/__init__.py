"""Rendering: pybullet scenes from maze specs (online), the offline render cache, and the maze as
a Foxglove scene for `run.mcap` (:mod:`cobelrun.render.foxglove_scene`)."""
