"""Fusion of the windows' panoptic renders into row-level fruit ids (the panoptic_fusion stage's algorithm).

The path of one pixel:
1. association.py: the windows' slots become local fruits, then row fruits (`associate`); each rendered
   pixel's slot maps to a row fruit id.
2. evidence.py: in each frame the renders of the windows that rendered it give one render label per pixel
   (`render_label`); `frame_evidence` adds the detector segment, and from the fruit models (models.py) the
   distance of the pixel's 3D point to each candidate fruit's sphere, seen surface and centre.
3. assignment.py: the pixel takes the option (background or a fruit) of least cost, a weighted sum of five terms.
4. rounds.py: with refine_rounds > 0 every frame is assigned, the models are refitted (seen surfaces grown,
   fruits the detector shows as several split), and the frames are assigned again; the last round is written.
"""
from rowmap.fusion.assignment import WEIGHTS, assign, cost, terms
from rowmap.fusion.association import associate, local_fruits, slot_views
from rowmap.fusion.evidence import Evidence, Frame, frame_evidence, render_label
from rowmap.fusion.models import FruitModel, FruitModels, fit_models, update
from rowmap.fusion.rounds import default_threads, fuse, fused_label, in_order
from rowmap.fusion.settings import TERMS, Config

__all__ = ["WEIGHTS", "TERMS", "Config", "Evidence", "Frame", "FruitModel", "FruitModels", "assign", "associate",
           "cost", "default_threads", "fit_models", "frame_evidence", "fuse", "fused_label", "in_order",
           "local_fruits", "render_label", "slot_views", "terms", "update"]
