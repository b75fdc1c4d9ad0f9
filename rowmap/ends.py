"""Fruits at a recording's ends, tracked by the detector where the fused frames are too few to see them.

Only every few frames is fused (a window's validation frames), so a fruit that enters the view in the
recording's last frames, or leaves it in the first, lies in one fused frame at most: too few for fruit_count to
tell it from a stray fragment; so does every fruit seen only in the frames of a window that failed. The detector
segments every frame. In these zones (end_zones), each fruit segment is un-projected with the sensor depth and the
segments are linked from frame to frame by their 3D centres into tracks. fruit_count counts a track seen in
enough frames that no counted fruit explains.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from nerf.geometry import pose_matrix
from nerf.surfaces import robust_centre, runs_by_key, unproject
from rowmap.detections import fruit_labels
from rowmap.geometry import POSE_COLS, subsample, with_sensor_depth
from rowmap.scoring import reference_pixels

MIN_SPAN_FRAMES = 3
"""frames: a track counts only from its first to its last segment spanning at least this many frames; a fruit in
view for one or two frames at a recording's very end is a glimpse (evaluate leaves such fruits out as well)."""
MAX_GAP_FRAMES = 2
"""frames: a track takes a segment at most this many frames after its last one (the detector misses a fruit
in a frame now and then)."""


@dataclass
class Track:
    """One fruit's detector segments in consecutive end-zone frames."""

    frames: list[int] = field(default_factory=list)
    points: list[np.ndarray] = field(default_factory=list)   # [N, 3] world points per segment
    depths: list[np.ndarray] = field(default_factory=list)   # [N] camera depths per segment
    classes: list[int] = field(default_factory=list)         # the detector's class per segment
    ref_px: list[float] = field(default_factory=list)        # pixels with depth per segment, as at 320x180
    centre: np.ndarray | None = None                         # [3] the last segment's robust centre

    @property
    def span(self) -> int:
        """frames from the first segment to the last, both included."""
        return self.frames[-1] - self.frames[0] + 1


def end_zones(fused: list[int], recorded: list[int]) -> list[int]:
    """The recorded frames where a fruit in view can lie in fewer than two fused frames. The fused frames fall
    into runs, split where two lie more than twice their median spacing apart (the frames of a window that
    failed, or the recording's ends); a run covers the frames from its second fused frame to its last but one,
    and every other frame is in the zones."""
    fused, covered = sorted(fused), np.zeros(len(recorded), bool)
    frames = np.array(sorted(recorded))
    if len(fused) >= 2:
        gap = 2 * float(np.median(np.diff(fused)))
        cuts = np.flatnonzero(np.diff(fused) > gap) + 1
        for run in np.split(np.array(fused), cuts):
            if len(run) >= 3:
                covered |= (frames >= run[1]) & (frames <= run[-2])
    return frames[~covered].tolist()


def row_pose(fid: int, fused_c2w: dict[int, np.ndarray], odometry: dict[int, np.ndarray]) -> np.ndarray:
    """[4, 4] frame `fid`'s camera in the row frame: the nearest fused frame's row-frame pose moved by the
    odometry between the two (over a few frames the odometry drifts by nothing that matters)."""
    anchor = min(fused_c2w, key=lambda f: (abs(f - fid), f))
    return fused_c2w[anchor] @ np.linalg.inv(odometry[anchor]) @ odometry[fid]


def segment_views(frame, c2w: np.ndarray, data_root: Path, dropped: np.ndarray | None, max_points: int
                  ) -> list[tuple[int, np.ndarray, np.ndarray, float]]:
    """(class id, world points [N, 3], depths [N], reference pixels) of each detector fruit segment of one frame
    (a row of frames.parquet), un-projected with the sensor depth; pixels without depth are left out, and at
    most max_points per segment are kept (evenly subsampled). Reference pixels: its pixels with depth as in a
    320x180 image (rowmap.scoring.reference_pixels)."""
    labels = fruit_labels(frame, data_root, dropped)
    if labels is None or not labels[1].any():
        return []
    sem, seg = labels
    depth = with_sensor_depth(np.zeros(seg.shape), data_root / frame.depth_path, frame.depth_scale_m)
    k = np.array([frame.fx, frame.fy, frame.cx, frame.cy], np.float64)
    v_all, u_all = np.nonzero((seg > 0) & (depth > 0))
    v_all, u_all, _, starts, ends = runs_by_key(v_all, u_all, seg[v_all, u_all])   # each segment's pixels, in order
    out = []
    for s0, s1 in zip(starts, ends):
        ref = float(reference_pixels(int(s1 - s0), seg.size))
        pick = s0 + subsample(int(s1 - s0), max_points)
        v, u = v_all[pick], u_all[pick]
        out.append((int(np.bincount(sem[v, u]).argmax()), unproject(depth, k, c2w, v, u), depth[v, u], ref))
    return out


def link(views: list[tuple[int, list[tuple]]], link_m: float, min_points: int) -> list[Track]:
    """Tracks of the segments `views` ((frame, segment_views) in frame order): each segment with at least
    min_points points joins the track whose last centre lies nearest, within link_m and MAX_GAP_FRAMES, that has
    no segment of this frame yet (nearest pairs first), else starts a track."""
    tracks: list[Track] = []
    for fid, segs in views:
        segs = [(*s, robust_centre(s[1])[0]) for s in segs if len(s[1]) >= min_points]
        open_ = [t for t in tracks if fid - t.frames[-1] <= MAX_GAP_FRAMES]
        pairs = sorted((float(np.linalg.norm(t.centre - s[-1])), i, j)
                       for i, t in enumerate(open_) for j, s in enumerate(segs))
        taken_t, taken_s = set(), set()
        for d, i, j in pairs:
            if d <= link_m and i not in taken_t and j not in taken_s:
                taken_t.add(i)
                taken_s.add(j)
                extend(open_[i], fid, segs[j])
        for j, s in enumerate(segs):
            if j not in taken_s:
                tracks.append(extend(Track(), fid, s))
    return tracks


def extend(track: Track, fid: int, seg: tuple) -> Track:
    """`track` with segment `seg` (segment_views' tuple and its robust centre) of frame `fid` added."""
    cls, pts, depth, ref, centre = seg
    track.frames.append(fid)
    track.ref_px.append(ref)
    track.points.append(pts)
    track.depths.append(depth)
    track.classes.append(cls)
    track.centre = centre
    return track


def end_tracks(frames: pd.DataFrame, fused: pd.DataFrame, data_root: Path, dropped: dict[int, np.ndarray],
               link_m: float, max_points: int, min_points: int) -> list[Track]:
    """The detector's tracks in the end zones of a recording (`frames`: frames.parquet indexed by frame id;
    `fused`: panoptic_frames, whose poses place the frames in the row frame), linked within link_m (m)."""
    if fused.empty:
        return []
    fused_c2w = dict(zip(fused.frame_id.astype(int), pose_matrix(fused[list(POSE_COLS)].to_numpy(np.float64))))
    zone = end_zones(list(fused_c2w), frames.index.astype(int).tolist())
    odometry = dict(zip(frames.index.astype(int), pose_matrix(frames[list(POSE_COLS)].to_numpy(np.float64))))
    views = [(f, segment_views(frames.loc[f], row_pose(f, fused_c2w, odometry), data_root, dropped.get(f),
                               max_points)) for f in zone]
    return link(views, link_m, min_points)
