"""Baselines trained in the same harness as ours (trainer.fit_window, panoptic.train.fit_panoptic), on the same
windows, for `pag bench compare`: the settings that turn our model into each of them.

Semantic-NeRF-like (Zhi et al., 2021): the MLP field on a Fourier encoding (NerfConfig field_kind='mlp_pe',
nerf/fields/mlp_pe.py), a semantic head on the trunk's features and NO instance output (SEMANTIC_ONLY). Its
semantic head is trained after the colour phase on the shared trunk (grid_mode 'shared', so the semantic
loss reaches the trunk) instead of jointly from step 0.

Panoptic-Lifting-like: our permutohedral field with fixed poses (NerfConfig refine_poses=False), one grid for
colour and panoptic (grid_mode 'shared') and plain linear assignment (id_window off): PANOPTIC_LIFTING_LIKE.
"""
from __future__ import annotations

OURS_OFF = dict(memory_prior=0.0, stuff_confidence=1.0, complete_3d=False)
"""this project's additions to the panoptic phase, off for the baselines: the slot memory, the 3D instance
completion and the lower weight of stuff labels (a pixel without detection)."""
SEMANTIC_ONLY = dict(grid_mode="shared", instances=False, id_window=False, **OURS_OFF)
"""PanopticConfig changes of the Semantic-NeRF-like baseline: semantic head on the trunk, no instances."""
PANOPTIC_LIFTING_LIKE = dict(grid_mode="shared", id_window=False, **OURS_OFF)
"""PanopticConfig changes of the Panoptic-Lifting-like baseline (plus NerfConfig refine_poses=False)."""
