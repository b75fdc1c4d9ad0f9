"""Panoptic scoring of rendered or detected frames against ground truth: PQ / SQ / RQ, mIoU and fruit-ID
consistency, accumulated over frames. The evaluate stage and the benchmarks score with this one class."""
from __future__ import annotations

import numpy as np

from nerf.panoptic_metrics import ConfusionAccumulator, PanopticAccumulator, dominant_ids, id_consistency, id_failures
from nerf.config import BASE_PIXELS
from pipeline.classes import DEFAULT_CLASSES, N_CLASSES, THING_IDS

STUFF_IDS = tuple(c.id for c in DEFAULT_CLASSES if not c.is_thing)


def reference_pixels(n_pixels: int | np.ndarray, image_pixels: int | np.ndarray) -> float | np.ndarray:
    """`n_pixels` of an image of `image_pixels` pixels counted as in a 320x180 image (nerf.config.BASE_PIXELS):
    scaled down for larger images, never up. A fruit covers the same reference pixels at every image size
    (the same share of the view), so a rule in reference pixels means the same at 320x180 and 1280x720."""
    return n_pixels * np.minimum(1.0, BASE_PIXELS / np.asarray(image_pixels, np.float64))


def image_pixels_for(reference_px: int, image_pixels: int) -> int:
    """The pixel count of an image of `image_pixels` pixels that `reference_px` reference pixels stand for
    (the inverse of reference_pixels, rounded up): a threshold in reference pixels for one image."""
    return int(np.ceil(reference_px * max(1.0, image_pixels / BASE_PIXELS) - 1e-9))


def thing_instances(sem: np.ndarray, inst: np.ndarray) -> np.ndarray:
    """Instance ids on thing pixels only (stuff pixels 0)."""
    return np.where(np.isin(sem, THING_IDS), inst, 0)


class PanopticScore:
    """PQ / SQ / RQ, mIoU and fruit-ID consistency of one set of (pred, gt) panoptic images. A fruit takes
    part in the ID consistency of a frame where it shows at least `min_visible_px` reference pixels
    (reference_pixels: pixels as in a 320x180 image)."""

    def __init__(self, min_visible_px: int = 1) -> None:
        self.min_visible_px = min_visible_px
        self.pq = PanopticAccumulator(things=set(THING_IDS), stuff=set(STUFF_IDS))
        self.conf = ConfusionAccumulator(N_CLASSES)
        self.ids: list[dict[int, int]] = []
        self.n = 0

    def update(self, p_sem: np.ndarray, p_inst: np.ndarray, g_sem: np.ndarray, g_inst: np.ndarray,
               fruit_ids: np.ndarray) -> None:
        self.add(self.image(p_sem, p_inst, g_sem, g_inst, fruit_ids))

    def image(self, p_sem: np.ndarray, p_inst: np.ndarray, g_sem: np.ndarray, g_inst: np.ndarray,
              fruit_ids: np.ndarray) -> PanopticScore:
        """A new score holding one image (self is not changed): images scored on several threads, then added
        in frame order, give what update() gives."""
        one = PanopticScore(self.min_visible_px)
        one.pq = self.pq.image(p_sem, p_inst, g_sem, g_inst)
        one.conf.matrix = self.conf.image(p_sem, g_sem)
        one.ids = [dominant_ids(g_inst, thing_instances(p_sem, p_inst), fruit_ids,
                                min_px=image_pixels_for(self.min_visible_px, g_inst.size))]
        one.n = 1
        return one

    def add(self, other: PanopticScore) -> None:
        """Add another score's images after this one's."""
        self.pq.add(other.pq)
        self.conf.matrix += other.conf.matrix
        self.ids += other.ids
        self.n += other.n

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
