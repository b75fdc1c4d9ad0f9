"""The optional colmap_poses stage: the alignment maths on exact data, the fallbacks, and COLMAP itself on a
small synthetic row (registration rate and aligned error against ground truth), then nerf_fit starting from it."""
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from nerf.geometry import align_similarity, apply_similarity, pose_matrix, rotation_angle_deg
from pipeline import cli
from pipeline.stage import StageContext
from rowmap.window_data import initial_poses
from schemas import validate
from stages import colmap_poses as cp
from stages import nerf_fit


def row_poses(n=8, seed=0, spacing_m=0.1) -> np.ndarray:
    """Cameras along a straight row (x; 0.7 m for 8 frames, like a 41-frame window), looking sideways (OpenCV camera: z = world -y), slightly jittered."""
    rng = np.random.default_rng(seed)
    base = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]).T  # columns: camera x, y, z in the world
    out = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        out[i, :3, :3] = Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix() @ base
        out[i, :3, 3] = [spacing_m * i, 0.1, 0.75]
    return out


def similarity(c2w, s, r, t):
    return apply_similarity(s, r, t, c2w)


def test_alignment_recovers_a_similarity_from_collinear_cameras_thanks_to_orientations():
    odo = row_poses()
    r = Rotation.from_euler("xyz", [30, -50, 120], degrees=True).as_matrix()
    # the "COLMAP" frame: odo = s R col + t  <=>  col = R^T (odo - t) / s
    s, t = 0.02, np.array([0.3, -1.0, 2.0])
    col = similarity(odo, 1 / s, r.T, -r.T @ t / s)
    s_hat, r_hat, t_hat = align_similarity(col[:, :3, 3], odo[:, :3, 3], col[:, :3, :3], odo[:, :3, :3])
    assert s_hat == pytest.approx(s, rel=1e-9)
    assert np.allclose(r_hat, r, atol=1e-9) and np.allclose(t_hat, t, atol=1e-9)
    back = similarity(col, s_hat, r_hat, t_hat)
    assert np.allclose(back, odo, atol=1e-9)
    # Umeyama on the centres alone (weight 0): the roll about the (almost) straight row is a guess
    s0, r0, t0 = align_similarity(col[:, :3, 3], odo[:, :3, 3], orientation_weight=0.0)
    assert np.allclose(similarity(col, s0, r0, t0)[:, :3, 3], odo[:, :3, 3], atol=1e-3)
    assert rotation_angle_deg(r0, r) > 1.0


def test_alignment_rejects_degenerate_input():
    p = np.zeros((4, 3))
    with pytest.raises(ValueError, match="coincide"):
        align_similarity(p, p + 1)
    with pytest.raises(ValueError, match="N >= 2"):
        align_similarity(np.zeros((1, 3)), np.zeros((1, 3)))


def test_window_alignment_falls_back_per_frame_and_per_window():
    odo = row_poses(8)
    col = similarity(odo, 50.0, np.eye(3), np.array([1.0, 2, 3]))
    cfg = cp.Config(enabled=True)
    ids = np.arange(10, 18)
    reg = {int(f): col[i] for i, f in enumerate(ids) if i not in (2, 5)}   # 2 frames not registered
    reg[16] = reg[16].copy()
    reg[16][:3, 3] += 50.0 * np.array([0.3, 0, 0])                          # one 30 cm outlier
    df, counts = cp.align_window(4, ids, odo, reg, cfg)
    validate(df, "colmap_poses")
    assert df["source"].tolist() == ["colmap", "colmap", "odometry", "colmap", "colmap", "odometry", "odometry", "colmap"]
    assert counts["frames_not_registered"] == 2 and counts["frames_rejected_residual"] == 1
    used = df[df.registered]
    assert used["residual_m"].max() < 1e-9 and used["window_rmse_m"].iloc[0] < 1e-9
    assert used["scale"].iloc[0] == pytest.approx(1 / 50.0)
    assert df.loc[6, "residual_m"] == pytest.approx(0.3, abs=0.02)
    assert np.allclose(pose_matrix(df[cp.POSE_COLS].to_numpy()), odo, atol=1e-9)  # fallback poses = odometry
    # too few frames: the whole window keeps odometry
    df2, counts2 = cp.align_window(4, ids, odo, {10: col[0], 11: col[1]}, cfg)
    assert not df2["registered"].any() and counts2["windows_without_colmap"] == 1
    assert df2["window_rmse_m"].isna().all() and df2["residual_m"].isna().all()


def test_disabled_stage_writes_an_empty_valid_table():
    ctx = StageContext(stage="colmap_poses", seq="t", data_root=Path("."), show_progress=False)
    out = cp.run({}, cp.Config(), ctx)["colmap_poses"]
    assert out.empty and validate(out, "colmap_poses").num_rows == 0
    assert "disabled" in ctx.summary["notes"][0]


def test_bad_config_is_a_clear_error():
    with pytest.raises(ValueError, match="min_registered must be >= 2"):
        cp.Config(min_registered=1)


def test_nerf_fit_initial_poses_from_colmap_and_clear_errors():
    w = pd.DataFrame({"frame_id": [3, 4], **{c: [0.0, 1.0] for c in cp.POSE_COLS}})
    same = initial_poses(w, 0, None, "odometry")
    assert same["pose_source"].tolist() == ["odometry"] * 2
    with pytest.raises(ValueError, match="colmap_poses.parquet is missing; run `pag colmap_poses"):
        initial_poses(w, 0, None, "colmap")
    col = pd.DataFrame({"window_id": [0, 0], "frame_id": [4, 3], "source": ["colmap", "odometry"],
                        **{c: [5.0, 1.0] for c in cp.POSE_COLS}})
    got = initial_poses(w, 0, col, "colmap")
    assert got["tx"].tolist() == [1.0, 5.0] and got["pose_source"].tolist() == ["odometry", "colmap"]
    with pytest.raises(ValueError, match="no pose for window 1"):
        initial_poses(w, 1, col, "colmap")


# -- COLMAP on a synthetic row ----------------------------------------------------------------------
# 64 x 40 px (the e2e row) gives SIFT too few features; 256 x 144 is the smallest size that registered every
# frame reliably (160 x 96 registers 13-16 frames of 16, but short windows there are marginal).
ROW = ["--set", "synth.n_frames=20", "--set", "synth.width=256", "--set", "synth.height=144",
       "--set", "synth.n_labelled=2", "--set", "synth.supersample=1", "--set", "synth.workers=2",
       "--set", "synth.write_bag=false", "--set", "windows.half_width=6", "--set", "colmap_poses.enabled=true"]


@pytest.fixture(scope="module")
def colmap_row(tmp_path_factory):
    pytest.importorskip("pycolmap", reason="pycolmap cannot be imported here")
    root = tmp_path_factory.mktemp("colmap") / "data"
    before = {p.name for p in Path(tempfile.gettempdir()).glob("pag_colmap_*")}
    assert cli.main(["all", "--seq", "synth_colmap", "--data-root", str(root), "--no-progress", "--to", "colmap_poses",
                     *ROW]) == 0
    after = {p.name for p in Path(tempfile.gettempdir()).glob("pag_colmap_*")}
    assert after <= before, "COLMAP work dirs left behind"
    return root


def test_colmap_registers_the_row_and_aligns_it_to_within_centimetres(colmap_row):
    interim = colmap_row / "interim" / "synth_colmap"
    poses = pd.read_parquet(interim / "colmap_poses.parquet")
    windows = pd.read_parquet(interim / "windows.parquet")
    assert len(poses) == len(windows) and set(poses.window_id) == {0, 1}
    assert poses["registered"].mean() >= 0.8
    assert (poses["source"] == np.where(poses["registered"], "colmap", "odometry")).all()
    gt = pd.read_parquet(colmap_row / "raw" / "synth_colmap" / "gt" / "poses.parquet").set_index("frame_id")
    reg = poses[poses.registered]
    err = np.linalg.norm(reg[["tx", "ty", "tz"]].to_numpy() - gt.loc[reg.frame_id, ["tx", "ty", "tz"]].to_numpy(), axis=1)
    assert err.max() < 0.03
    rot = rotation_angle_deg(pose_matrix(reg[cp.POSE_COLS].to_numpy())[:, :3, :3],
                             pose_matrix(gt.loc[reg.frame_id, cp.POSE_COLS].to_numpy())[:, :3, :3])
    assert rot.max() < 3.0
    assert (reg["window_rmse_m"] < 0.02).all() and (reg["scale"] > 0).all()
    # nothing but the declared outputs was written
    assert not list(colmap_row.rglob("*.db")) and not list(colmap_row.rglob("sparse"))


class _Payloads(Exception):
    """Raised by the stand-in for the Dask map: carries what nerf_fit would hand its window tasks."""


def test_nerf_fit_hands_its_windows_the_colmap_poses(colmap_row, tmp_path, monkeypatch):
    interim = colmap_row / "interim" / "synth_colmap"
    inputs = {p.stem: pd.read_parquet(p) for p in interim.glob("*.parquet")}

    def no_fit(fn, payloads, **kw):
        raise _Payloads(payloads)

    monkeypatch.setattr(nerf_fit.parallel, "map_tasks", no_fit)
    ctx = StageContext(stage="nerf_fit", seq="synth_colmap", data_root=colmap_row, staging={"nerf": tmp_path},
                       show_progress=False)
    with pytest.raises(_Payloads) as got:
        nerf_fit.run(inputs, nerf_fit.Config(pose_source="colmap"), ctx)
    col = inputs["colmap_poses"]
    for key, payload in got.value.args[0].items():
        frames = pd.DataFrame(payload["frames"]).set_index("frame_id")
        c = col[col.window_id == int(key)].set_index("frame_id").loc[frames.index]
        assert (frames["pose_source"] == c["source"]).all() and (frames["pose_source"] == "colmap").any()
        assert np.allclose(frames[cp.POSE_COLS].to_numpy(), c[cp.POSE_COLS].to_numpy())
    with pytest.raises(_Payloads) as got:
        nerf_fit.run(inputs, nerf_fit.Config(), ctx)
    frames = pd.DataFrame(got.value.args[0]["0"]["frames"]).set_index("frame_id")
    odo = inputs["frames"].set_index("frame_id").loc[frames.index]
    assert (frames["pose_source"] == "odometry").all() and np.allclose(frames[cp.POSE_COLS], odo[cp.POSE_COLS])


def test_compare_bench_runs_colmap_itself_when_the_table_lacks_the_window(colmap_row, tmp_path):
    from bench.compare import colmap_window
    seq = "synth_colmap"
    interim = colmap_row / "interim" / seq
    frames, windows = pd.read_parquet(interim / "frames.parquet"), pd.read_parquet(interim / "windows.parquet")
    w = windows[windows.window_id == 1].merge(frames, on="frame_id")
    kept = w.iloc[::2].reset_index(drop=True)
    from_table, note = colmap_window(seq, colmap_row, windows, kept, 1)
    assert note == "" and (from_table["pose_source"] == "colmap").any()
    # a data/ whose colmap_poses table lacks window 1: the bench runs the stage on that window itself
    bare = tmp_path / "data"
    for rel in (f"raw/{seq}", f"interim/{seq}/images", f"interim/{seq}/frames.parquet", f"interim/{seq}/windows.parquet"):
        (bare / rel).parent.mkdir(parents=True, exist_ok=True)
        (bare / rel).symlink_to(colmap_row / rel)
    table = pd.read_parquet(interim / "colmap_poses.parquet")
    table[table.window_id != 1].to_parquet(bare / "interim" / seq / "colmap_poses.parquet")
    own, note = colmap_window(seq, bare, windows, kept, 1)
    assert note.startswith("COLMAP run by the bench") and len(own) == len(kept)
    assert (own["frame_id"].to_numpy() == kept["frame_id"].to_numpy()).all()
    assert not (bare / "interim" / seq / "colmap_poses.parquet").is_symlink()
    assert len(pd.read_parquet(bare / "interim" / seq / "colmap_poses.parquet")) == len(table[table.window_id != 1])
    reg = (own["pose_source"] == "colmap").to_numpy() & (from_table["pose_source"] == "colmap").to_numpy()
    assert reg.sum() >= len(kept) // 2
    # the same images and settings (one COLMAP thread, the default): both land within a centimetre of each other
    d = np.linalg.norm(own.loc[reg, ["tx", "ty", "tz"]].to_numpy() - from_table.loc[reg, ["tx", "ty", "tz"]].to_numpy(), axis=1)
    assert d.max() < 0.01
