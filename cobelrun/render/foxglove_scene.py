"""The maze as a Foxglove scene: ``foxglove.SceneEntity`` objects built from an env's
:class:`~cobelrun.envs.base.Geometry` (walls, floor or arena outline, graph, labelled regions),
and the colours and heights of the paths monitors draw over it.

:class:`cobelrun.io.mcap.McapRecorder` writes these entities on ``/maze`` (and the paths on
``/run_NNNN/<name>``); building them needs only the geometry, not the file.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    CubePrimitive,
    CylinderPrimitive,
    KeyValuePair,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

if TYPE_CHECKING:
    from cobelrun.envs.base import Geometry

__all__ = ["FRAME_ID", "PATH_COLORS", "PATH_HEIGHT", "scene_entities", "scene_pose"]

#: frame of every pose, scene entity and label
FRAME_ID = "maze"


def scene_pose(x: float, y: float, z: float = 0.0, heading: float = 0.0) -> Pose:
    """A ``foxglove.Pose`` at ``(x, y, z)`` turned by ``heading`` radians about +z."""
    return Pose(
        position=Vector3(x=x, y=y, z=z),
        orientation=Quaternion(x=0.0, y=0.0, z=math.sin(heading / 2), w=math.cos(heading / 2)),
    )


_WALL = Color(r=0.35, g=0.35, b=0.4, a=1.0)
_FLOOR = Color(r=0.88, g=0.88, b=0.85, a=1.0)
_DOOR = Color(r=0.85, g=0.45, b=0.1, a=0.45)
_DOOR_ARROW = Color(r=0.85, g=0.45, b=0.1, a=1.0)
_GRAPH = Color(r=0.3, g=0.45, b=0.7, a=1.0)
_LABEL = Color(r=0.1, g=0.1, b=0.1, a=1.0)
# regions get colours in turn; their names are written next to them
_REGION_COLORS = [
    Color(r=0.2, g=0.7, b=0.3, a=0.8),
    Color(r=0.2, g=0.4, b=0.9, a=0.8),
    Color(r=0.9, g=0.55, b=0.1, a=0.8),
    Color(r=0.7, g=0.2, b=0.7, a=0.8),
    Color(r=0.9, g=0.2, b=0.2, a=0.8),
]
#: colours of monitors' paths (replay events) by kind: highlighted against the maze
PATH_COLORS = {
    "forward": Color(r=1.0, g=0.5, b=0.0, a=1.0),
    "reverse": Color(r=0.9, g=0.1, b=0.6, a=1.0),
    "mixed": Color(r=0.6, g=0.2, b=0.9, a=1.0),
    "none": Color(r=1.0, g=0.8, b=0.1, a=1.0),
}
PATH_HEIGHT = 0.3  # world units above the floor
WALL_HEIGHT = 0.5  # in cell sizes
WALL_THICKNESS = 0.06  # in cell sizes
DOOR_HEIGHT = 0.2  # in cell sizes: one-way doors are low panels, not walls


def scene_entities(geometry: Geometry, timestamp: Timestamp | None = None) -> list[SceneEntity]:
    """The maze as ``foxglove.SceneEntity`` objects (frame ``maze``).

    Entities: ``floor`` (free grid cells as flat cubes, or the arena outline as a closed line),
    ``walls`` (one thin cube per wall segment, ``WALL_HEIGHT`` cells high), ``doors`` (each
    one-way door a low translucent panel with an arrow across it in the direction it can be
    passed; absent where the layout has none), ``graph`` (nodes as
    spheres, edges as a line list) and ``regions`` (a flat cylinder per point or circle region,
    a closed line per polygon, each with its name as a text label).
    """
    g = geometry
    s = g.cell_size if g.cell_size > 0 else 1.0
    ts = timestamp if timestamp is not None else Timestamp(0, 0)

    def entity(name: str, **prims: Any) -> SceneEntity:
        return SceneEntity(
            timestamp=ts,
            frame_id=FRAME_ID,
            id=name,
            metadata=[KeyValuePair(key="kind", value=g.kind)],
            **prims,
        )

    out: list[SceneEntity] = []
    floor_cubes = [
        CubePrimitive(
            pose=scene_pose(x, y, -0.01 * s),
            size=Vector3(x=s * 0.96, y=s * 0.96, z=0.02 * s),
            color=_FLOOR,
        )
        for x, y in g.cells.tolist()
    ]
    floor_lines = []
    if len(g.outline):
        floor_lines.append(
            LinePrimitive(
                type=LinePrimitiveLineType.LineLoop,
                pose=scene_pose(0.0, 0.0),
                thickness=0.05 * s,
                points=[Point3(x=x, y=y, z=0.0) for x, y in g.outline.tolist()],
                color=_WALL,
            )
        )
    if floor_cubes or floor_lines:
        out.append(entity("floor", cubes=floor_cubes, lines=floor_lines))
    if len(g.walls):
        walls = []
        for x0, y0, x1, y1 in g.walls.tolist():
            length = math.hypot(x1 - x0, y1 - y0)
            angle = math.atan2(y1 - y0, x1 - x0)
            walls.append(
                CubePrimitive(
                    pose=scene_pose((x0 + x1) / 2, (y0 + y1) / 2, WALL_HEIGHT * s / 2, angle),
                    size=Vector3(
                        x=length + WALL_THICKNESS * s, y=WALL_THICKNESS * s, z=WALL_HEIGHT * s
                    ),
                    color=_WALL,
                )
            )
        out.append(entity("walls", cubes=walls))
    if len(g.doors):
        panels, arrows = [], []
        for x0, y0, x1, y1, dx, dy in g.doors.tolist():
            length = math.hypot(x1 - x0, y1 - y0)
            mx, my = (x0 + x1) / 2, (y0 + y1) / 2
            panels.append(
                CubePrimitive(
                    pose=scene_pose(mx, my, DOOR_HEIGHT * s / 2, math.atan2(y1 - y0, x1 - x0)),
                    size=Vector3(x=length, y=WALL_THICKNESS * s / 2, z=DOOR_HEIGHT * s),
                    color=_DOOR,
                )
            )
            arrows.append(
                ArrowPrimitive(
                    pose=scene_pose(mx - 0.3 * s * dx, my - 0.3 * s * dy, 0.05 * s,
                                    math.atan2(dy, dx)),
                    shaft_length=0.4 * s, shaft_diameter=0.05 * s, head_length=0.2 * s,
                    head_diameter=0.15 * s, color=_DOOR_ARROW,
                )
            )  # fmt: skip
        out.append(entity("doors", cubes=panels, arrows=arrows))
    if len(g.nodes) and len(g.edges):  # a graph (a grid's nodes are its cells: drawn as floor)
        nodes = [
            SpherePrimitive(
                pose=scene_pose(x, y, 0.05 * s),
                size=Vector3(x=0.1 * s, y=0.1 * s, z=0.1 * s),
                color=_GRAPH,
            )
            for x, y in g.nodes.tolist()
        ]
        pts = [Point3(x=x, y=y, z=0.05 * s) for x, y in g.nodes[g.edges.reshape(-1)].tolist()]
        edges = LinePrimitive(type=LinePrimitiveLineType.LineList, pose=scene_pose(0.0, 0.0),
                              thickness=0.02 * s, points=pts, color=_GRAPH)  # fmt: skip
        out.append(entity("graph", spheres=nodes, lines=[edges]))
    if g.regions:
        cylinders, lines, texts = [], [], []
        labels_at: dict[tuple[float, float], int] = {}  # regions at one spot: labels stacked
        for i, (name, reg) in enumerate(sorted(g.regions.items())):
            color = _REGION_COLORS[i % len(_REGION_COLORS)]
            shape = reg.get("shape", "point")
            if shape == "polygon":
                pts2 = np.asarray(reg["points"], np.float64).reshape(-1, 2)
                lines.append(LinePrimitive(
                    type=LinePrimitiveLineType.LineLoop, pose=scene_pose(0.0, 0.0),
                    thickness=0.04 * s, color=color,
                    points=[Point3(x=x, y=y, z=0.02 * s) for x, y in pts2.tolist()],
                ))  # fmt: skip
                x, y = pts2.mean(axis=0).tolist()
            else:
                x, y = float(reg["x"]), float(reg["y"])
                d = 2.0 * float(reg["radius"]) if shape == "circle" else 0.6 * s
                cylinders.append(CylinderPrimitive(
                    pose=scene_pose(x, y, 0.02 * s), size=Vector3(x=d, y=d, z=0.04 * s),
                    bottom_scale=1.0, top_scale=1.0, color=color,
                ))  # fmt: skip
            above = labels_at[(x, y)] = labels_at.get((x, y), -1) + 1
            texts.append(TextPrimitive(pose=scene_pose(x, y, (0.3 + 0.25 * above) * s), billboard=True,
                                       font_size=12.0,
                                       scale_invariant=True, color=_LABEL, text=name))  # fmt: skip
        out.append(entity("regions", cylinders=cylinders, lines=lines, texts=texts))
    return out
