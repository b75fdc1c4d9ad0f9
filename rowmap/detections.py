"""The detector's fruit segments of one frame, as the fused stages read them."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.classes import THING_IDS
from pipeline.images import ImageError, read_label


def dropped_segments(dets: pd.DataFrame | None) -> dict[int, np.ndarray]:
    """{frame id: segment ids the depth filter dropped} from the detections_filtered table (`kept` False)."""
    if dets is None or dets.empty:
        return {}
    gone = dets[~dets.kept.astype(bool)]
    return {int(f): g.segment_id.to_numpy() for f, g in gone.groupby("frame_id")}


def fruit_segments(frame, data_root: Path, dropped: np.ndarray | None = None) -> np.ndarray | None:
    """[H, W] int64: the detector's segment id on each pixel of a fruit segment (0 elsewhere: stuff, void,
    and the segment ids in `dropped`), or None where the frame has no detector output. `frame` is a row of
    frames.parquet."""
    labels = fruit_labels(frame, data_root, dropped)
    return None if labels is None else labels[1]


def fruit_labels(frame, data_root: Path, dropped: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """(the detector's semantic PNG [H, W], fruit_segments' map [H, W]) of one frame, each file read once; None
    where the frame has no detector output."""
    sp, ip = frame.det_semantic_path, frame.det_instance_path
    if not isinstance(sp, str) or not isinstance(ip, str):
        return None
    sem = read_label(data_root / sp, "detector semantic")
    inst = read_label(data_root / ip, "detector instance").astype(np.int64)
    if sem.shape != inst.shape or sem.shape != (int(frame.height), int(frame.width)):
        raise ImageError(f"frame {int(frame.frame_id)}: detector PNGs {sp} / {ip} are {sem.shape} / {inst.shape}, "
                         f"the images are {(int(frame.height), int(frame.width))}")
    inst[~np.isin(sem, THING_IDS)] = 0
    if dropped is not None and len(dropped):
        inst[np.isin(inst, dropped)] = 0
    return sem, inst
