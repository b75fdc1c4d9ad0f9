"""Fusion of the windows' panoptic renders into row-level fruit ids (the panoptic_fusion stage's algorithm).

A pixel's path (docs/fusion.md): association.py cuts each window's slots into local fruits and joins them across
windows into row fruits; models.py fits each row fruit a sphere and a seen surface; evidence.py says what the
render, the detector and the candidates' models show at the pixel; assignment.py gives it the option of least
cost, refits the models, and assigns again."""
from rowmap.fusion.assignment import cost, fuse, fused_label, terms
from rowmap.fusion.association import slot_views
from rowmap.fusion.evidence import Frame, frame_evidence
from rowmap.fusion.models import FruitModel, FruitModels, fit_models
from rowmap.fusion.settings import TERMS, Config

__all__ = ["TERMS", "Config", "Frame", "FruitModel", "FruitModels", "cost", "fit_models",
           "frame_evidence", "fuse", "fused_label", "slot_views", "terms"]
