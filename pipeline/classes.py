"""Semantic classes shared by the synthetic row, the detector files and the model."""
from __future__ import annotations

from dataclasses import dataclass

VOID = 255
"""Semantic PNG value for void / unlabelled pixels."""


@dataclass(frozen=True)
class SemanticClass:
    id: int
    name: str
    is_thing: bool
    """Things (fruits) have instances; stuff (background, plant) does not."""
    rgb: tuple[int, int, int]
    """Display colour in figures."""


DEFAULT_CLASSES: tuple[SemanticClass, ...] = (
    SemanticClass(0, "background", False, (60, 60, 60)),
    SemanticClass(1, "plant", False, (40, 160, 60)),
    SemanticClass(2, "fruit_green", True, (120, 220, 60)),
    SemanticClass(3, "fruit_mixed", True, (240, 170, 30)),
    SemanticClass(4, "fruit_red", True, (220, 30, 30)),
)

THING_IDS: tuple[int, ...] = tuple(c.id for c in DEFAULT_CLASSES if c.is_thing)
N_CLASSES: int = len(DEFAULT_CLASSES)


def class_name(class_id: int) -> str:
    for c in DEFAULT_CLASSES:
        if c.id == class_id:
            return c.name
    raise KeyError(f"unknown class id {class_id}; classes: {[(c.id, c.name) for c in DEFAULT_CLASSES]}")
