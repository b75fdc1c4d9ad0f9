"""Fusion of the windows' panoptic renders into row-level fruit ids (the panoptic_fusion stage's algorithm).

One module per step of a pixel's path (docs/fusion.md): association.py turns the windows' slots into row
fruits; models.py fits each fruit a sphere and a seen surface; evidence.py says, per pixel of a frame, what
the render, the detector and the models show; assignment.py gives the pixel the option of least cost;
rounds.py assigns every frame, refits the models and assigns again."""
from rowmap.fusion.assignment import cost, terms
from rowmap.fusion.association import slot_views
from rowmap.fusion.evidence import Frame, frame_evidence, render_label
from rowmap.fusion.models import FruitModel, FruitModels, fit_models
from rowmap.fusion.rounds import fuse, fused_label
from rowmap.fusion.settings import TERMS, Config

__all__ = ["TERMS", "Config", "Frame", "FruitModel", "FruitModels", "cost", "fit_models",
           "frame_evidence", "fuse", "fused_label", "render_label", "slot_views", "terms"]
