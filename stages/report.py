"""One self-contained HTML page a person reads first: config, per-window quality, images, fruit map, counts, scores."""
from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass

import cv2
import numpy as np
import pandas as pd

from pipeline.classes import DEFAULT_CLASSES, THING_IDS, VOID
from pipeline.dag import STAGE_ORDER
from pipeline.images import read_label, read_rgb
from pipeline.provenance import stage_costs
from pipeline.stage import StageContext
from rowmap.colours import id_colours
from rowmap.renders import Renders

INPUTS = ("frames", "windows", "window_metrics", "nerf", "renders", "panoptic_frames", "panoptic", "fruits", "counts")
OPTIONAL_INPUTS = ("evaluation", "input_checks")
OUTPUTS = ("report",)

SECTIONS = ("Run configuration", "Windows", "Centre frames", "Fruit map", "Counts", "Evaluation", "Input checks",
            "Cost per stage")


@dataclass(frozen=True)
class Config:
    image_width_px: int = 320
    """pixels, >= 16: width of each image in the centre-frame panels (nearest-neighbour scaled). The page
    embeds every image, so wider panels make a larger HTML file."""
    max_windows_shown: int = 12
    """windows, >= 1: centre-frame panels for at most this many windows (evenly spread over the row); raise it
    to inspect every window of a long row."""

    def __post_init__(self) -> None:
        if self.image_width_px < 16 or self.max_windows_shown < 1:
            raise ValueError("report.image_width_px must be >= 16 and report.max_windows_shown >= 1")


def png_data_uri(img: np.ndarray) -> str:
    """RGB or grey uint8 image -> 'data:image/png;base64,...'."""
    bgr = cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if img.ndim == 3 else img
    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise ValueError("report: could not encode a PNG")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode()


def colour_panoptic(sem: np.ndarray, inst: np.ndarray) -> np.ndarray:
    """Stuff in its class colour, each thing instance in its own colour, void black. [H, W, 3] uint8."""
    out = np.zeros(sem.shape + (3,), np.uint8)
    for c in DEFAULT_CLASSES:
        out[sem == c.id] = c.rgb
    thing = np.isin(sem, THING_IDS) & (inst > 0)
    if thing.any():
        ids, inv = np.unique(inst[thing], return_inverse=True)
        out[thing] = id_colours(ids)[inv]
    out[sem == VOID] = 0
    return out


def colour_depth(depth_mm: np.ndarray, max_m: float = 2.5) -> np.ndarray:
    d = np.clip(depth_mm.astype(np.float32) / 1000 / max_m, 0, 1)
    img = cv2.applyColorMap((255 * (1 - d)).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    img[depth_mm == 0] = 0
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def scaled(img: np.ndarray, width: int) -> np.ndarray:
    h, w = img.shape[:2]
    return cv2.resize(img, (width, max(1, round(h * width / w))), interpolation=cv2.INTER_NEAREST)


def draw_ids(img: np.ndarray, inst: np.ndarray) -> np.ndarray:
    """Write each fruit id at its mask's centroid (img already scaled; inst at original size)."""
    out = img.copy()
    sx, sy = img.shape[1] / inst.shape[1], img.shape[0] / inst.shape[0]
    for i in np.unique(inst[inst > 0]):
        v, u = np.nonzero(inst == i)
        p = (int(u.mean() * sx) - 6, int(v.mean() * sy) + 4)
        cv2.putText(out, str(int(i)), p, cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(out, str(int(i)), p, cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def table_html(df: pd.DataFrame, floatfmt: str = "{:.4g}") -> str:
    return df.to_html(index=False, border=0, classes="t", na_rep="-",
                      float_format=lambda v: floatfmt.format(v))


def top_down_map(fruits: pd.DataFrame, frames: pd.DataFrame) -> str:
    """Matplotlib figure: fruits (x vs y, world) coloured by class, sized by diameter, with the camera path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 3.6), dpi=110)
    ax.plot(frames.tx, frames.ty, "-", color="0.4", lw=1, label="camera path (odometry)")
    counted = fruits.counted.astype(bool)
    for c in DEFAULT_CLASSES:
        if not c.is_thing:
            continue
        for near, marker in ((True, "o"), (False, "x")):
            f = fruits[(fruits.class_id == c.id) & (counted == near)]
            if len(f):
                size = 40 * (f.diameter_m.fillna(0.07).clip(0.02, 0.15).to_numpy() / 0.07) ** 2
                ax.scatter(f.x_m, f.y_m, s=size if near else 25, marker=marker, color=np.array(c.rgb) / 255,
                           edgecolors="k" if near else None, linewidths=0.5,
                           label=f"{c.name}{'' if near else ' (far row or fragment, not counted)'} ({len(f)})")
    for f in fruits[counted].itertuples():
        ax.annotate(str(f.fruit_id), (f.x_m, f.y_m), fontsize=6, ha="center", va="bottom",
                    xytext=(0, 5), textcoords="offset points")
    ax.set_xlabel("x along the row [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))
    ax.set_title("Fruit map, top view (world frame)")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def centre_panels(inputs: dict, cfg: Config, ctx: StageContext) -> str:
    frames = inputs["frames"].set_index("frame_id", drop=False)
    metrics: pd.DataFrame = inputs["window_metrics"]
    pf = inputs["panoptic_frames"].set_index("frame_id", drop=False)
    renders = Renders(inputs["renders"], ctx.data_root)
    ok = metrics[metrics.status == "ok"].sort_values("window_id")
    if len(ok) > cfg.max_windows_shown:
        ok = ok.iloc[np.round(np.linspace(0, len(ok) - 1, cfg.max_windows_shown)).astype(int)]
    heads = ["input RGB", "detector panoptic", "NeRF RGB render", "fused panoptic (fruit ids)", "NeRF depth"]
    rows = []
    for m in ok.itertuples(index=False):
        wid, fid = int(m.window_id), int(m.center_frame_id)
        fr = frames.loc[fid]
        w = cfg.image_width_px
        cells = [scaled(read_rgb(ctx.abspath(fr.rgb_path)), w)]
        if isinstance(fr.det_semantic_path, str) and isinstance(fr.det_instance_path, str):
            cells.append(scaled(colour_panoptic(read_label(ctx.abspath(fr.det_semantic_path), "detector semantic"),
                                                read_label(ctx.abspath(fr.det_instance_path), "detector instance")), w))
        else:
            cells.append(None)
        rgb = renders.relpath(wid, fid, "rgb")
        cells.append(scaled(read_rgb(ctx.abspath(rgb)), w) if rgb else None)
        if fid in pf.index:
            p = pf.loc[fid]
            inst = read_label(ctx.abspath(p.instance_path), "fused instance")
            img = scaled(colour_panoptic(read_label(ctx.abspath(p.semantic_path), "fused semantic"), inst), w)
            cells.append(draw_ids(img, inst))
        else:
            cells.append(None)
        dpath = renders.relpath(wid, fid, "depth")
        cells.append(scaled(colour_depth(read_label(ctx.abspath(dpath), "depth render")), w) if dpath else None)
        tds = "".join(f'<td><img src="{png_data_uri(c)}" alt="{h}"></td>' if c is not None else "<td>(none)</td>"
                      for c, h in zip(cells, heads))
        rows.append(f"<tr><th>window {wid}<br>frame {fid}</th>{tds}</tr>")
    if not rows:
        return "<p>No fitted window.</p>"
    head = "".join(f"<th>{h}</th>" for h in heads)
    return f'<table class="img"><tr><th></th>{head}</tr>{"".join(rows)}</table>'


CSS = """body{font-family:system-ui,sans-serif;margin:1.5em;max-width:1800px;color:#222}
h1{font-size:1.5em}h2{font-size:1.2em;border-bottom:1px solid #ccc;margin-top:1.6em}
table.t{border-collapse:collapse;font-size:0.85em}table.t td,table.t th{padding:2px 8px;border-bottom:1px solid #eee;
text-align:right}table.img td{padding:2px}table.img img{display:block}pre{background:#f6f6f6;padding:0.6em;
max-height:24em;overflow:auto;font-size:0.8em}.note{color:#a40}"""


def stage_costs_html(ctx: StageContext) -> str:
    """Wall time and peak memory of each stage that made this row's outputs (the runner's manifest records;
    the report stage itself is still running, so it is left out)."""
    costs = stage_costs(ctx.data_root, ctx.seq, [s for s in STAGE_ORDER if s != ctx.stage])
    costs = costs[costs.seconds.notna()]
    if not len(costs):
        return "<p>No stage records found.</p>"
    total = pd.DataFrame([{"stage": "total", "seconds": costs.seconds.sum(), "peak_rss_mb": costs.peak_rss_mb.max(),
                           "code_version": ""}])
    shown = pd.concat([costs, total], ignore_index=True).rename(columns={"peak_rss_mb": "peak memory (MiB)"})
    return ("<p>Wall time of each stage and the largest resident memory of the pipeline process and its "
            "workers while it ran, for the run that produced the stage's current outputs (a stage skipped as "
            "up to date keeps the cost of the run that made it; code_version = the commit it ran).</p>"
            + table_html(shown))


def input_checks_html(checks: pd.DataFrame | None) -> str:
    """What ingest counted (skips, repairs, totals) and its notes (README.md, section Bad input)."""
    if checks is None or checks.empty:
        return "<p>No input checks recorded (run `pag ingest`).</p>"
    counts = checks[checks.check != "note"].copy()
    counts["value"] = [str(c) if pd.notna(c) else n for c, n in zip(counts["count"], counts["note"])]
    notes = checks[checks.check == "note"].note
    out = "<p>What ingest read, skipped and repaired (a skipped frame or segment is counted here, never " \
          "dropped silently).</p>" + table_html(counts[["check", "value"]])
    if len(notes):
        out += "<ul>" + "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>"
    return out


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    metrics: pd.DataFrame = inputs["window_metrics"]
    fruits: pd.DataFrame = inputs["fruits"]
    counts: pd.DataFrame = inputs["counts"]
    evaluation: pd.DataFrame | None = inputs.get("evaluation")
    # the runner writes the resolved config of every run next to the outputs before any stage runs
    cfg_file = ctx.data_root / "processed" / ctx.seq / "config.resolved.yaml"
    cfg_text = cfg_file.read_text() if cfg_file.is_file() else f"({cfg_file} not found)"
    wtab = metrics[["window_id", "center_frame_id", "status", "preset", "device", "n_train", "n_val", "params",
                    "steps", "fit_s", "render_s_per_image", "val_psnr"]].copy()
    if evaluation is not None and len(evaluation):
        per = evaluation[evaluation.scope.str.startswith("window_")]
        piv = per.pivot(index="scope", columns="metric", values="value")
        for k in ("pq", "miou", "pq_detector", "miou_detector", "id_consistency", "ate_odometry_m", "ate_refined_m"):
            if k in piv:
                wtab[k] = [piv[k].get(f"window_{w:03d}", np.nan) for w in wtab.window_id]
    near = fruits[fruits.counted.astype(bool)]
    parts = [f"<h1>PAg-NeRF phenotyping report: {html.escape(ctx.seq)}</h1>",
             f"<p>{len(near)} near-row fruits counted ({len(fruits) - len(near)} far-row fruits, fragments or fruits "
             f"the detector does not confirm not "
             f"counted) in "
             f"{int((metrics.status == 'ok').sum())} of {len(metrics)} windows.</p>"]
    failed = metrics[metrics.status != "ok"]
    if len(failed):
        parts.append("<p class='note'>Failed windows (not fused): " + ", ".join(
            f"{int(r.window_id)} ({html.escape(str(r.error))})" for r in failed.itertuples()) + "</p>")
    parts += [f"<h2>{SECTIONS[0]}</h2><pre>{html.escape(cfg_text)}</pre>",
              f"<h2>{SECTIONS[1]}</h2><p>Quality (PSNR on validation frames; PQ and mIoU of the panoptic renders "
              f"against ground truth where it exists) and cost per window.</p>" + table_html(wtab),
              f"<h2>{SECTIONS[2]}</h2>" + centre_panels(inputs, cfg, ctx),
              f"<h2>{SECTIONS[3]}</h2>"]
    if len(fruits):
        parts.append(f'<img src="{top_down_map(fruits, inputs["frames"])}" alt="fruit map">')
        cols = ["fruit_id", "class_name", "class_confidence", "x_m", "y_m", "z_m", "diameter_m", "height_m",
                "median_depth_m", "n_frames", "n_confirmed_frames", "n_windows", "first_frame_id", "last_frame_id"]
        parts.append("<details><summary>near-row fruits</summary>" + table_html(near[cols]) + "</details>")
    else:
        parts.append("<p>No fruit was fused (no panoptic renders?).</p>")
    parts.append(f"<h2>{SECTIONS[4]}</h2>" + table_html(counts) + f"<p>Total: {int(counts['count'].sum())}</p>")
    parts.append(f"<h2>{SECTIONS[5]}</h2>")
    if evaluation is not None and len(evaluation):
        row = evaluation[evaluation.scope.isin(["row", "windows_mean"])]
        piv = row.pivot(index="metric", columns="scope", values="value").reset_index()
        parts.append(table_html(piv))
    else:
        parts.append("<p>No evaluation (the sequence has no ground truth, or `pag evaluate` has not run).</p>")
    parts.append(f"<h2>{SECTIONS[6]}</h2>" + input_checks_html(inputs.get("input_checks")))
    parts.append(f"<h2>{SECTIONS[7]}</h2>" + stage_costs_html(ctx))
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>PAg-NeRF report {html.escape(ctx.seq)}"
            f"</title><style>{CSS}</style></head><body>{''.join(parts)}</body></html>")
    out = ctx.output_dir("report") / "report.html"
    out.write_text(page, encoding="utf-8")
    ctx.summary.update(report=ctx.relpath("report", "report.html"), kib=round(len(page) / 1024))
    return {}
