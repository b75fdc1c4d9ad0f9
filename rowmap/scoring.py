"""Panoptic scoring of rendered or detected frames against ground truth: PQ / SQ / RQ, mIoU and fruit-ID
consistency, accumulated over frames. The evaluate stage and the benchmarks score with this one class."""
from __future__ import annotations

import numpy as np

from nerf.panoptic_metrics import ConfusionAccumulator, PanopticAccumulator, dominant_ids, id_consistency, id_failures
from pipeline.classes import DEFAULT_CLASSES, N_CLASSES, THING_IDS

STUFF_IDS = tuple(c.id for c in DEFAULT_CLASSES if not c.is_thing)


def thing_instances(sem: np.ndarray, inst: np.ndarray) -> np.ndarray:
    """Instance ids on thing pixels only (stuff pixels 0)."""
    return np.where(np.isin(sem, THING_IDS), inst, 0)


class PanopticScore:
    """PQ / SQ / RQ, mIoU and fruit-ID consistency of one set of (pred, gt) panoptic images."""

    def __init__(self, min_visible_px: int = 1) -> None:
        self.min_visible_px = min_visible_px
        self.pq = PanopticAccumulator(things=set(THING_IDS), stuff=set(STUFF_IDS))
        self.conf = ConfusionAccumulator(N_CLASSES)
        self.ids: list[dict[int, int]] = []
        self.n = 0

    def update(self, p_sem: np.ndarray, p_inst: np.ndarray, g_sem: np.ndarray, g_inst: np.ndarray,
               fruit_ids: np.ndarray) -> None:
        self.pq.update(p_sem, p_inst, g_sem, g_inst)
        self.conf.update(p_sem, g_sem)
        self.ids.append(dominant_ids(g_inst, thing_instances(p_sem, p_inst), fruit_ids, min_px=self.min_visible_px))
        self.n += 1

    def metrics(self, min_frames: int, suffix: str = "") -> dict[str, float]:
        if not self.n:
            return {}
        pq = self.pq.compute()
        out = {f"pq{suffix}": pq["pq"], f"sq{suffix}": pq["sq"], f"rq{suffix}": pq["rq"],
               f"pq_things{suffix}": pq["pq_things"], f"pq_stuff{suffix}": pq["pq_stuff"],
               f"miou{suffix}": self.conf.miou()}
        if not suffix:
            share, n = id_consistency(self.ids, min_frames)
            out.update(id_consistency=share, id_consistency_n_fruits=float(n))
            out.update({f"id_fail_{k}": float(v) for k, v in id_failures(self.ids, min_frames).items()})
        return out
