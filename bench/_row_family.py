"""The family of synthetic rows that `pag bench rows` judges the pipeline on.

Fixed: the rows were chosen before any setting was tuned on them and are not changed to suit a result (a
new row gets a new name; an existing row keeps its knobs). They span the knobs a season's rows vary in:
fruit density 8-40 fruits/m, detector miss rate 0.05-0.35, false positives 0.1-0.6 per frame, merged
detections 0.02-0.15, odometry drift up to 0.06 m/m and 4 deg/m, and 120-240 frames (1.6-3.2 m of row).
Every row keeps one labelled frame (one window) per 40 frames, as the default row has. Every other synth
setting is the `small` preset's default (320x180).
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FamilyRow:
    name: str
    """short name; the sequence is synth_rows_<name>."""
    doc: str
    """what the row stands for."""
    seed: int
    fruits_per_m: float
    det_miss_rate: float
    det_false_pos_rate: float
    det_merge_rate: float
    odom_drift_m_per_m: float
    odom_yaw_drift_deg_per_m: float
    n_frames: int

    @property
    def n_labelled(self) -> int:
        return self.n_frames // 40

    def knobs(self) -> dict[str, float]:
        """The synth settings this row sets (synth.<key>)."""
        return {"seed": self.seed, "fruits_per_m": self.fruits_per_m, "det_miss_rate": self.det_miss_rate,
                "det_false_pos_rate": self.det_false_pos_rate, "det_merge_rate": self.det_merge_rate,
                "odom_drift_m_per_m": self.odom_drift_m_per_m,
                "odom_yaw_drift_deg_per_m": self.odom_yaw_drift_deg_per_m, "n_frames": self.n_frames,
                "n_labelled": self.n_labelled}


FAMILY: tuple[FamilyRow, ...] = (
    FamilyRow("typical", "a typical row: the default row's knobs on another seed",
              seed=101, fruits_per_m=12, det_miss_rate=0.15, det_false_pos_rate=0.3, det_merge_rate=0.05,
              odom_drift_m_per_m=0.03, odom_yaw_drift_deg_per_m=2.0, n_frames=120),
    FamilyRow("sparse_clean", "few fruits, a good detector and good odometry: the easy end",
              seed=102, fruits_per_m=8, det_miss_rate=0.05, det_false_pos_rate=0.1, det_merge_rate=0.02,
              odom_drift_m_per_m=0.01, odom_yaw_drift_deg_per_m=0.5, n_frames=120),
    FamilyRow("medium_long", "medium density over a longer row (6 windows)",
              seed=103, fruits_per_m=16, det_miss_rate=0.10, det_false_pos_rate=0.2, det_merge_rate=0.05,
              odom_drift_m_per_m=0.02, odom_yaw_drift_deg_per_m=1.5, n_frames=240),
    FamilyRow("dense", "a dense row with a typical detector",
              seed=104, fruits_per_m=30, det_miss_rate=0.15, det_false_pos_rate=0.3, det_merge_rate=0.08,
              odom_drift_m_per_m=0.03, odom_yaw_drift_deg_per_m=2.0, n_frames=180),
    FamilyRow("densest", "the densest row: 40 fruits/m, 20 % missed, few false positives, many merges",
              seed=105, fruits_per_m=40, det_miss_rate=0.20, det_false_pos_rate=0.15, det_merge_rate=0.10,
              odom_drift_m_per_m=0.03, odom_yaw_drift_deg_per_m=2.0, n_frames=160),
    FamilyRow("poor_detector", "a weak detector: a third of the fruits missed, many false positives and merges",
              seed=106, fruits_per_m=20, det_miss_rate=0.35, det_false_pos_rate=0.6, det_merge_rate=0.12,
              odom_drift_m_per_m=0.02, odom_yaw_drift_deg_per_m=1.0, n_frames=120),
    FamilyRow("bad_odometry", "the worst odometry: 0.06 m/m and 4 deg/m of drift",
              seed=107, fruits_per_m=16, det_miss_rate=0.15, det_false_pos_rate=0.3, det_merge_rate=0.05,
              odom_drift_m_per_m=0.06, odom_yaw_drift_deg_per_m=4.0, n_frames=200),
    FamilyRow("dense_hard", "everything at once: dense, a noisy detector, strong drift, a long row",
              seed=108, fruits_per_m=35, det_miss_rate=0.25, det_false_pos_rate=0.45, det_merge_rate=0.15,
              odom_drift_m_per_m=0.05, odom_yaw_drift_deg_per_m=3.0, n_frames=240),
)
"""The family, in a fixed order."""

HOLDOUT: tuple[FamilyRow, ...] = (
    FamilyRow("holdout_mid", "between typical and dense, on a seed no family row uses",
              seed=201, fruits_per_m=22, det_miss_rate=0.18, det_false_pos_rate=0.35, det_merge_rate=0.07,
              odom_drift_m_per_m=0.035, odom_yaw_drift_deg_per_m=2.5, n_frames=160),
    FamilyRow("holdout_dense", "dense with a noisy detector, knob values no family row has",
              seed=202, fruits_per_m=33, det_miss_rate=0.28, det_false_pos_rate=0.5, det_merge_rate=0.11,
              odom_drift_m_per_m=0.04, odom_yaw_drift_deg_per_m=3.0, n_frames=200),
    FamilyRow("holdout_sparse_drift", "sparse with strong drift",
              seed=203, fruits_per_m=10, det_miss_rate=0.12, det_false_pos_rate=0.2, det_merge_rate=0.03,
              odom_drift_m_per_m=0.05, odom_yaw_drift_deg_per_m=3.5, n_frames=160),
)
"""Held-out rows of the same kind (`pag bench rows --holdout`): seeds and knob values that are in no family
row, fixed before they were first run. A mechanism tuned to the family's rows shows as a gap between the two
tables; no setting is ever chosen on these rows."""

UNSEEN: tuple[FamilyRow, ...] = (
    FamilyRow("unseen_light", "light fruiting, a good detector, mild drift",
              seed=301, fruits_per_m=14, det_miss_rate=0.08, det_false_pos_rate=0.25, det_merge_rate=0.04,
              odom_drift_m_per_m=0.025, odom_yaw_drift_deg_per_m=1.2, n_frames=140),
    FamilyRow("unseen_dense", "dense, a typical-to-noisy detector, strong drift",
              seed=302, fruits_per_m=27, det_miss_rate=0.22, det_false_pos_rate=0.4, det_merge_rate=0.09,
              odom_drift_m_per_m=0.045, odom_yaw_drift_deg_per_m=2.8, n_frames=220),
    FamilyRow("unseen_crowded", "crowded, many misses and merges, good odometry",
              seed=303, fruits_per_m=38, det_miss_rate=0.30, det_false_pos_rate=0.55, det_merge_rate=0.13,
              odom_drift_m_per_m=0.015, odom_yaw_drift_deg_per_m=0.8, n_frames=170),
    FamilyRow("unseen_weak_drift", "a weak detector and strong drift on a medium row",
              seed=304, fruits_per_m=18, det_miss_rate=0.40, det_false_pos_rate=0.7, det_merge_rate=0.06,
              odom_drift_m_per_m=0.055, odom_yaw_drift_deg_per_m=3.8, n_frames=150),
    FamilyRow("unseen2_medium", "medium density, a good detector, mild drift",
              seed=401, fruits_per_m=24, det_miss_rate=0.13, det_false_pos_rate=0.28, det_merge_rate=0.065,
              odom_drift_m_per_m=0.022, odom_yaw_drift_deg_per_m=1.6, n_frames=130),
    FamilyRow("unseen2_dense", "dense, a noisy detector, drift between typical and strong",
              seed=402, fruits_per_m=31, det_miss_rate=0.26, det_false_pos_rate=0.42, det_merge_rate=0.095,
              odom_drift_m_per_m=0.038, odom_yaw_drift_deg_per_m=2.6, n_frames=190),
    FamilyRow("unseen2_sparse_weak", "sparse, a weak detector, strong drift",
              seed=403, fruits_per_m=11, det_miss_rate=0.32, det_false_pos_rate=0.48, det_merge_rate=0.085,
              odom_drift_m_per_m=0.042, odom_yaw_drift_deg_per_m=3.2, n_frames=125),
    FamilyRow("unseen2_crowded_merges", "crowded with many merges, few false positives, good odometry",
              seed=404, fruits_per_m=36, det_miss_rate=0.17, det_false_pos_rate=0.22, det_merge_rate=0.125,
              odom_drift_m_per_m=0.028, odom_yaw_drift_deg_per_m=1.4, n_frames=135),
    FamilyRow("unseen3_medium", "medium density, a typical detector, typical drift",
              seed=501, fruits_per_m=17, det_miss_rate=0.11, det_false_pos_rate=0.33, det_merge_rate=0.055,
              odom_drift_m_per_m=0.032, odom_yaw_drift_deg_per_m=2.2, n_frames=145),
    FamilyRow("unseen3_dense", "dense, a typical detector, mild drift",
              seed=502, fruits_per_m=29, det_miss_rate=0.19, det_false_pos_rate=0.37, det_merge_rate=0.085,
              odom_drift_m_per_m=0.027, odom_yaw_drift_deg_per_m=1.9, n_frames=175),
    FamilyRow("unseen3_crowded", "crowded, many merges, drift between typical and strong",
              seed=503, fruits_per_m=34, det_miss_rate=0.21, det_false_pos_rate=0.31, det_merge_rate=0.115,
              odom_drift_m_per_m=0.036, odom_yaw_drift_deg_per_m=2.4, n_frames=165),
    FamilyRow("unseen3_weak", "a weak detector and strong drift at medium density",
              seed=504, fruits_per_m=21, det_miss_rate=0.29, det_false_pos_rate=0.52, det_merge_rate=0.075,
              odom_drift_m_per_m=0.047, odom_yaw_drift_deg_per_m=3.3, n_frames=135),
    FamilyRow("unseen4_medium", "medium density, a good detector, typical drift",
              seed=601, fruits_per_m=19, det_miss_rate=0.14, det_false_pos_rate=0.27, det_merge_rate=0.06,
              odom_drift_m_per_m=0.029, odom_yaw_drift_deg_per_m=1.7, n_frames=155),
    FamilyRow("unseen4_dense", "dense, a noisy detector, mild drift",
              seed=602, fruits_per_m=32, det_miss_rate=0.24, det_false_pos_rate=0.39, det_merge_rate=0.09,
              odom_drift_m_per_m=0.024, odom_yaw_drift_deg_per_m=2.1, n_frames=185),
    FamilyRow("unseen4_crowded", "crowded, few misses, drift between typical and strong",
              seed=603, fruits_per_m=37, det_miss_rate=0.16, det_false_pos_rate=0.34, det_merge_rate=0.105,
              odom_drift_m_per_m=0.041, odom_yaw_drift_deg_per_m=2.7, n_frames=150),
    FamilyRow("unseen4_weak", "a weak detector and strong drift at light density",
              seed=604, fruits_per_m=15, det_miss_rate=0.31, det_false_pos_rate=0.46, det_merge_rate=0.068,
              odom_drift_m_per_m=0.052, odom_yaw_drift_deg_per_m=3.6, n_frames=130),
    FamilyRow("unseen5_medium", "medium density, a good detector, typical drift",
              seed=701, fruits_per_m=23, det_miss_rate=0.125, det_false_pos_rate=0.29, det_merge_rate=0.058,
              odom_drift_m_per_m=0.033, odom_yaw_drift_deg_per_m=2.3, n_frames=152),
    FamilyRow("unseen5_dense", "dense, a noisy detector, mild drift",
              seed=702, fruits_per_m=28, det_miss_rate=0.215, det_false_pos_rate=0.41, det_merge_rate=0.088,
              odom_drift_m_per_m=0.026, odom_yaw_drift_deg_per_m=1.8, n_frames=172),
    FamilyRow("unseen5_crowded", "crowded, many merges, few false positives, drift between typical and strong",
              seed=703, fruits_per_m=39, det_miss_rate=0.185, det_false_pos_rate=0.24, det_merge_rate=0.118,
              odom_drift_m_per_m=0.037, odom_yaw_drift_deg_per_m=2.45, n_frames=146),
    FamilyRow("unseen5_weak", "a weak detector and strong drift at light density",
              seed=704, fruits_per_m=13, det_miss_rate=0.33, det_false_pos_rate=0.51, det_merge_rate=0.072,
              odom_drift_m_per_m=0.048, odom_yaw_drift_deg_per_m=3.4, n_frames=138),
    FamilyRow("unseen6_medium", "medium density, a good detector, typical drift",
              seed=801, fruits_per_m=25, det_miss_rate=0.135, det_false_pos_rate=0.32, det_merge_rate=0.062,
              odom_drift_m_per_m=0.031, odom_yaw_drift_deg_per_m=2.05, n_frames=142),
    FamilyRow("unseen6_dense", "dense, a noisy detector, mild drift",
              seed=802, fruits_per_m=30.5, det_miss_rate=0.235, det_false_pos_rate=0.43, det_merge_rate=0.097,
              odom_drift_m_per_m=0.0285, odom_yaw_drift_deg_per_m=1.65, n_frames=168),
    FamilyRow("unseen6_crowded", "crowded, many merges, few false positives, drift between typical and strong",
              seed=803, fruits_per_m=38.5, det_miss_rate=0.165, det_false_pos_rate=0.26, det_merge_rate=0.123,
              odom_drift_m_per_m=0.043, odom_yaw_drift_deg_per_m=2.9, n_frames=158),
    FamilyRow("unseen6_weak", "a weak detector and strong drift at light density",
              seed=804, fruits_per_m=9.5, det_miss_rate=0.305, det_false_pos_rate=0.57, det_merge_rate=0.067,
              odom_drift_m_per_m=0.051, odom_yaw_drift_deg_per_m=3.55, n_frames=132),
    FamilyRow("unseen7_medium", "medium density, a good detector, typical drift",
              seed=901, fruits_per_m=23.5, det_miss_rate=0.145, det_false_pos_rate=0.305, det_merge_rate=0.0665,
              odom_drift_m_per_m=0.0335, odom_yaw_drift_deg_per_m=2.15, n_frames=148),
    FamilyRow("unseen7_dense", "dense, a noisy detector, mild drift",
              seed=902, fruits_per_m=31.5, det_miss_rate=0.245, det_false_pos_rate=0.445, det_merge_rate=0.092,
              odom_drift_m_per_m=0.0265, odom_yaw_drift_deg_per_m=1.75, n_frames=164),
    FamilyRow("unseen7_crowded", "crowded, many merges, few false positives, drift between typical and strong",
              seed=903, fruits_per_m=37.5, det_miss_rate=0.175, det_false_pos_rate=0.285, det_merge_rate=0.1185,
              odom_drift_m_per_m=0.0415, odom_yaw_drift_deg_per_m=2.65, n_frames=152),
    FamilyRow("unseen7_weak", "a weak detector and strong drift at light density",
              seed=904, fruits_per_m=11.5, det_miss_rate=0.315, det_false_pos_rate=0.545, det_merge_rate=0.0705,
              odom_drift_m_per_m=0.049, odom_yaw_drift_deg_per_m=3.45, n_frames=136),
    FamilyRow("unseen8_medium", "medium density, a good detector, typical drift",
              seed=1001, fruits_per_m=24.5, det_miss_rate=0.155, det_false_pos_rate=0.315, det_merge_rate=0.0635,
              odom_drift_m_per_m=0.0325, odom_yaw_drift_deg_per_m=2.25, n_frames=146),
    FamilyRow("unseen8_dense", "dense, a noisy detector, mild drift",
              seed=1002, fruits_per_m=32.5, det_miss_rate=0.255, det_false_pos_rate=0.455, det_merge_rate=0.094,
              odom_drift_m_per_m=0.0275, odom_yaw_drift_deg_per_m=1.85, n_frames=166),
    FamilyRow("unseen8_crowded", "crowded, many merges, few false positives, drift between typical and strong",
              seed=1003, fruits_per_m=36.5, det_miss_rate=0.1725, det_false_pos_rate=0.275, det_merge_rate=0.1215,
              odom_drift_m_per_m=0.0405, odom_yaw_drift_deg_per_m=2.55, n_frames=154),
    FamilyRow("unseen8_weak", "a weak detector and strong drift at light density",
              seed=1004, fruits_per_m=12.5, det_miss_rate=0.325, det_false_pos_rate=0.535, det_merge_rate=0.0685,
              odom_drift_m_per_m=0.0475, odom_yaw_drift_deg_per_m=3.35, n_frames=134),
    FamilyRow("unseen9_medium", "medium density, a good detector, typical drift",
              seed=1101, fruits_per_m=21.5, det_miss_rate=0.135, det_false_pos_rate=0.295, det_merge_rate=0.0595,
              odom_drift_m_per_m=0.0345, odom_yaw_drift_deg_per_m=2.35, n_frames=142),
    FamilyRow("unseen9_dense", "dense, a noisy detector, mild drift",
              seed=1102, fruits_per_m=33.5, det_miss_rate=0.265, det_false_pos_rate=0.465, det_merge_rate=0.0965,
              odom_drift_m_per_m=0.0265, odom_yaw_drift_deg_per_m=1.75, n_frames=170),
    FamilyRow("unseen9_crowded", "crowded, many merges, few false positives, drift between typical and strong",
              seed=1103, fruits_per_m=35.5, det_miss_rate=0.1775, det_false_pos_rate=0.265, det_merge_rate=0.1195,
              odom_drift_m_per_m=0.0415, odom_yaw_drift_deg_per_m=2.65, n_frames=158),
    FamilyRow("unseen9_weak", "a weak detector and strong drift at light density",
              seed=1104, fruits_per_m=14, det_miss_rate=0.335, det_false_pos_rate=0.525, det_merge_rate=0.0715,
              odom_drift_m_per_m=0.0485, odom_yaw_drift_deg_per_m=3.4, n_frames=138),
    FamilyRow("unseen10_medium", "medium density, a good detector, typical drift",
              seed=1201, fruits_per_m=22.5, det_miss_rate=0.145, det_false_pos_rate=0.285, det_merge_rate=0.0615,
              odom_drift_m_per_m=0.0335, odom_yaw_drift_deg_per_m=2.15, n_frames=144),
    FamilyRow("unseen10_dense", "dense, a noisy detector, mild drift",
              seed=1205, fruits_per_m=30.25, det_miss_rate=0.2475, det_false_pos_rate=0.435, det_merge_rate=0.0935,
              odom_drift_m_per_m=0.0289, odom_yaw_drift_deg_per_m=1.95, n_frames=163),
    FamilyRow("unseen10_crowded", "crowded, many merges, few false positives, drift between typical and strong",
              seed=1206, fruits_per_m=37.25, det_miss_rate=0.1825, det_false_pos_rate=0.255, det_merge_rate=0.1225,
              odom_drift_m_per_m=0.0395, odom_yaw_drift_deg_per_m=2.62, n_frames=156),
    FamilyRow("unseen10_weak", "a weak detector and strong drift at light density",
              seed=1204, fruits_per_m=13.5, det_miss_rate=0.34, det_false_pos_rate=0.515, det_merge_rate=0.0695,
              odom_drift_m_per_m=0.0495, odom_yaw_drift_deg_per_m=3.3, n_frames=140),
    FamilyRow("unseen11_medium", "medium density, a good detector, typical drift",
              seed=1301, fruits_per_m=20.75, det_miss_rate=0.1575, det_false_pos_rate=0.3075, det_merge_rate=0.0585,
              odom_drift_m_per_m=0.0315, odom_yaw_drift_deg_per_m=2.37, n_frames=147),
    FamilyRow("unseen11_dense", "dense, a noisy detector, mild drift",
              seed=1302, fruits_per_m=31.75, det_miss_rate=0.2325, det_false_pos_rate=0.4175, det_merge_rate=0.0975,
              odom_drift_m_per_m=0.0347, odom_yaw_drift_deg_per_m=2.47, n_frames=167),
    FamilyRow("unseen11_crowded", "crowded, many merges, few false positives, drift between typical and strong",
              seed=1303, fruits_per_m=36.25, det_miss_rate=0.1925, det_false_pos_rate=0.2675, det_merge_rate=0.1165,
              odom_drift_m_per_m=0.0425, odom_yaw_drift_deg_per_m=2.75, n_frames=157),
    FamilyRow("unseen11_weak", "a weak detector and strong drift at light density",
              seed=1304, fruits_per_m=15.25, det_miss_rate=0.3175, det_false_pos_rate=0.5475, det_merge_rate=0.0745,
              odom_drift_m_per_m=0.0465, odom_yaw_drift_deg_per_m=3.15, n_frames=137),
    FamilyRow("unseen12_medium", "medium density, a good detector, typical drift",
              seed=1401, fruits_per_m=19.25, det_miss_rate=0.1425, det_false_pos_rate=0.3225, det_merge_rate=0.0565,
              odom_drift_m_per_m=0.0305, odom_yaw_drift_deg_per_m=2.27, n_frames=151),
    FamilyRow("unseen12_dense", "dense, a noisy detector, mild drift",
              seed=1402, fruits_per_m=32.25, det_miss_rate=0.2425, det_false_pos_rate=0.4425, det_merge_rate=0.1015,
              odom_drift_m_per_m=0.0281, odom_yaw_drift_deg_per_m=1.83, n_frames=173),
    FamilyRow("unseen12_crowded", "crowded, many merges, few false positives, drift between typical and strong",
              seed=1403, fruits_per_m=38.75, det_miss_rate=0.1875, det_false_pos_rate=0.2475, det_merge_rate=0.1235,
              odom_drift_m_per_m=0.0411, odom_yaw_drift_deg_per_m=2.57, n_frames=161),
    FamilyRow("unseen12_weak", "a weak detector and strong drift at light density",
              seed=1404, fruits_per_m=13.25, det_miss_rate=0.3275, det_false_pos_rate=0.5575, det_merge_rate=0.0765,
              odom_drift_m_per_m=0.0455, odom_yaw_drift_deg_per_m=3.25, n_frames=143),
)
"""Unseen rows (`pag bench rows --unseen`): seeds and knob values in no family or held-out row. Their outputs
are read once, when a design is final, and reported as they come; nothing is tuned on them. The first four
were defined before the fusion redesign (issue 48) began and read once after it; the `unseen2_` rows were
defined after that reading, before the redesign's last changes, and are read once after them; the `unseen3_`
rows were defined on 2026-12-07, after the round refit (c4012cf) and before the changes that follow it, all
within the family's ranges, and are read once after those changes; the `unseen4_` rows were defined after
that reading (9f96e52), before the changes for the fruits at a recording's ends, and are read once after them;
the `unseen5_` rows were defined after that reading (97970ce), before the fusion's rules were measured one by
one and those that help no row dropped, and are read once after that; the `unseen6_` rows were defined after
the fix for fruits without a sphere (2506cc5), with no change of the fusion since, and are read once; the
`unseen7_` rows were defined after that reading (d5fb20b), before the next change, and read once after it;
the `unseen8_` rows were defined after that reading (a9104dc), before the next change, and read once after it;
the `unseen9_` rows were defined after that reading (15ad44c), before the next change, and read once after it;
the `unseen10_` rows were defined after that reading (1292a31), before any later change, and are read once after it
(unseen10_dense and unseen10_crowded as first defined, seeds 1202 and 1203, shared a miss rate with family rows and
were read once; they were then redefined with new seeds and knob values, and read once again); the `unseen11_`
rows, with values in no other row (unseen ones included), were defined after that reading (4c83c6c), before the
next change (the render's fruit probability, b38abc0), and read once after it; the `unseen12_` rows, with
values in no other row, were defined after that reading (f330276), before any later change, and are read once after it.
Rows beyond the family's 8-40 fruits/m or 0.35 miss rate (0.40, 0.7 false positives per frame) test that mechanisms
extrapolate."""

QUICK: tuple[str, ...] = ("typical", "dense", "poor_detector", "bad_odometry")
"""Rows of the `--quick` smoke run (with tiny images, few frames and few steps)."""


def family_row(name: str) -> FamilyRow:
    """The family, held-out or unseen row called `name`."""
    for r in (*FAMILY, *HOLDOUT, *UNSEEN):
        if r.name == name:
            return r
    raise ValueError(f"no row {name!r} in the family; rows: {[r.name for r in FAMILY]}, held out: "
                     f"{[r.name for r in HOLDOUT]}, unseen: {[r.name for r in UNSEEN]}")
