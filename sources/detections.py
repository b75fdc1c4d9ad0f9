"""Detector output in three formats, turned into the project's per-frame label images and segments.

- png_pair: the project's own files: `semantic/<stamp>.png` (8-bit class id, 255 = void),
  `instance/<stamp>.png` (16-bit segment id, 0 = none) and `scores.csv`.
- coco_panoptic: what Detectron2 / Mask2Former write: a JSON `{"annotations": [{"file_name",
  "image_id", "segments_info": [{"id", "category_id", "isthing", "score"?}]}], "categories"?: [...]}`
  and a folder of PNGs named like the JSON (panoptic.json + panoptic/) whose pixel id is
  R + 256 G + 256^2 B (0 = unlabelled).
- coco_instances: a COCO results JSON (Mask R-CNN, YOLO-seg exports): a list of {"image_id",
  "category_id", "segmentation" (RLE with a counts string or list, or polygons), "score"}, or a dict
  with such an "annotations" list plus "images" and "categories".

Every format is read into a `FrameLabels` per frame (project class ids after the class map) so the rest
of the pipeline sees one thing: a semantic map, an instance map and one (segment_id, class_id, score) per
thing segment. See docs/detector_formats.md.
"""
from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from pipeline.classes import DEFAULT_CLASSES, THING_IDS, VOID
from sources import coco
from sources.common import IngestError, StampUnit, pair_nearest, stamp_from_name

FORMATS = ("png_pair", "coco_panoptic", "coco_instances")
IMAGES_JSON = "images.json"
"""Sibling file with the COCO `images` list (id, file_name) for a results JSON that is a bare list."""


class UnreadableLabels(IngestError):
    """A frame's detector PNG is missing or cannot be decoded (ingest skips the frame's detections, counted,
    or stops, per ingest.on_bad_image)."""


@dataclass
class FrameLabels:
    semantic: np.ndarray
    """[H, W] uint8 project class ids, 255 = void."""
    instance: np.ndarray
    """[H, W] uint16 segment ids, 0 = stuff / none."""
    segments: list[tuple[int, int, float, int]]
    """(segment_id, class_id, score, area_px) per thing segment, by segment id."""


# -- class map --------------------------------------------------------------------------------------

def project_class(value: Any, where: str) -> int:
    """A project class given by id or name (or 'void' / 255) -> its id."""
    by_name = {c.name: c.id for c in DEFAULT_CLASSES}
    ids = {c.id for c in DEFAULT_CLASSES}
    if isinstance(value, str) and value.strip().lower() in ("void", "unlabelled", "ignore"):
        return VOID
    if isinstance(value, str) and value.strip() in by_name:
        return by_name[value.strip()]
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool) and (int(value) in ids or value == VOID):
        return int(value)
    if isinstance(value, str) and value.strip().isdigit() and (int(value) in ids or int(value) == VOID):
        return int(value)
    raise IngestError(f"{where}: {value!r} is not a project class; classes: "
                      f"{', '.join(f'{c.id}={c.name}' for c in DEFAULT_CLASSES)} (or void / 255)")


def load_class_map(spec: dict | str, raw: Path) -> tuple[dict[Any, int] | None, str]:
    """ingest.class_map -> ({detector category id or name: project class id}, origin), None = identity.

    `spec` is an inline mapping or the path of a YAML mapping file (relative paths are taken from the raw
    folder, so the file is part of the row's inputs)."""
    if spec in ("", None, {}):
        return None, ""
    origin = "ingest.class_map"
    if isinstance(spec, str):
        path = Path(spec) if Path(spec).is_absolute() else raw / spec
        if not path.is_file():
            raise IngestError(f"ingest.class_map: file {path} does not exist (relative paths are read from the raw "
                              f"folder {raw})")
        try:
            spec = yaml.safe_load(path.read_text())
        except yaml.YAMLError as err:
            raise IngestError(f"class map {path} is not valid YAML: {err}") from err
        origin = str(path)
        if isinstance(spec, dict) and isinstance(spec.get("class_map"), dict):
            spec = spec["class_map"]
    if not isinstance(spec, dict) or not spec:
        raise IngestError(f"{origin}: expected a mapping of detector category (id or name) to project class, "
                          f"e.g. {{1: fruit_red, leaf: plant}}; got {spec!r}")
    out: dict[Any, int] = {}
    for key, value in spec.items():
        k = int(key) if isinstance(key, str) and key.strip().isdigit() else key
        out[k.strip() if isinstance(k, str) else k] = project_class(value, f"{origin}, entry {key!r}")
    return out, origin


class ClassMapper:
    """Detector category id -> project class id, through the class map (names resolved with the detector's
    categories) or, without a map, taking detector ids as project ids. Unmapped categories are collected so
    the error can list them all."""

    def __init__(self, mapping: dict[Any, int] | None, origin: str, categories: dict[int, str], unmapped: str,
                 source: str):
        self.mapping = mapping
        self.origin = origin
        self.categories = categories
        """the detector's categories {id: name}, for names in the map and in errors."""
        self.unmapped = unmapped
        self.source = source
        """the detector file(s), for errors."""
        self.by_id: dict[int, int] = {}
        if mapping is not None:
            names = [k for k in mapping if isinstance(k, str)]
            if names and not categories:
                raise IngestError(f"{origin} maps category names {names} but {source} lists no categories "
                                  f"(id, name); map the detector's category ids instead")
            name_to_id = {v: k for k, v in categories.items()}
            unknown = [n for n in names if n not in name_to_id]
            if unknown:
                raise IngestError(f"{origin}: category name(s) {unknown} are not among the detector's categories "
                                  f"in {source}: {sorted(categories.values())}")
            for k, v in mapping.items():
                self.by_id[name_to_id[k] if isinstance(k, str) else int(k)] = v
        self.missing: set[int] = set()

    def __call__(self, category: int) -> int:
        category = int(category)
        if category in self.by_id:
            return self.by_id[category]
        if self.mapping is None and category in {c.id for c in DEFAULT_CLASSES}:
            return category
        self.missing.add(category)
        return VOID

    def lut(self, values: np.ndarray) -> np.ndarray:
        """Map a semantic PNG's values (255 stays void)."""
        out = np.full(256, VOID, np.uint8)
        for v in np.unique(values):
            if int(v) != VOID:
                out[int(v)] = self(int(v))
        return out[values]

    def check(self) -> int:
        """Raise if categories were unmapped (unless ingest.unmapped=void); return how many were voided."""
        if not self.missing:
            return 0
        if self.unmapped == "void":
            return len(self.missing)
        named = [f"{c} ({self.categories[c]})" if c in self.categories else str(c) for c in sorted(self.missing)]
        how = (f"add them to {self.origin}" if self.mapping is not None else
               "set ingest.class_map to map the detector's categories onto the project's classes")
        raise IngestError(f"{self.source}: detector categories {named} have no project class; {how}, or set "
                          f"ingest.unmapped=void to make them unlabelled. Classes: "
                          f"{', '.join(f'{c.id}={c.name}' for c in DEFAULT_CLASSES)}")


# -- finding the files ------------------------------------------------------------------------------

def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise IngestError(f"{path} is not valid JSON: {err}") from err
    except OSError as err:
        raise IngestError(f"{path} cannot be read: {err}") from err


def json_kind(obj: Any, path: Path) -> str:
    """'coco_panoptic', 'coco_instances' or '' for a parsed JSON (an empty annotations list is panoptic
    when the PNG folder named like the JSON exists)."""
    if isinstance(obj, list):
        return "coco_instances" if all(isinstance(a, dict) and "segmentation" in a for a in obj[:20]) else ""
    if isinstance(obj, dict) and isinstance(obj.get("annotations"), list):
        anns = obj["annotations"][:20]
        if not anns:
            return "coco_panoptic" if path.with_suffix("").is_dir() else "coco_instances"
        if all(isinstance(a, dict) and "segments_info" in a for a in anns):
            return "coco_panoptic"
        if all(isinstance(a, dict) and "segmentation" in a for a in anns):
            return "coco_instances"
    return ""


EXPECTED = {"coco_panoptic": "a dict whose annotations carry segments_info",
            "coco_instances": "a list of results with segmentation (or a dict whose annotations carry them)",
            "auto": "COCO panoptic (annotations with segments_info) or instance results (with segmentation)"}


def detect_format(det_dir: Path, wanted: str, json_name: str) -> tuple[str, Path | None, Any]:
    """Which format the detector folder holds -> (format, JSON path or None, parsed JSON or None).
    format is '' when the folder holds no detector output at all."""
    if not det_dir.is_dir():
        if wanted not in ("auto",):
            raise IngestError(f"ingest.detections_format={wanted} but the detector folder {det_dir} does not exist")
        return "", None, None
    present = sorted(p.name + ("/" if p.is_dir() else "") for p in det_dir.iterdir())
    if wanted == "png_pair" or (wanted == "auto" and (det_dir / "instance").is_dir()):
        missing = [d for d in ("semantic", "instance") if not (det_dir / d).is_dir()]
        if missing:
            raise IngestError(f"{det_dir}: the png_pair format needs semantic/ and instance/ folders; missing "
                              f"{missing}; the folder has: {present}")
        return "png_pair", None, None
    if json_name:
        cands = [det_dir / json_name]
        if not cands[0].is_file():
            raise IngestError(f"ingest.detections_json: {cands[0]} does not exist; {det_dir} has: {present}")
    else:
        cands = sorted(p for p in det_dir.glob("*.json") if p.name != IMAGES_JSON)
    found = []
    for p in cands:
        obj = read_json(p)
        kind = json_kind(obj, p)
        if kind and wanted in ("auto", kind):
            found.append((kind, p, obj))
        elif json_name:
            raise IngestError(f"{p} is not a {'COCO detections' if wanted == 'auto' else wanted} file: expected "
                              f"{EXPECTED[wanted]}; it is {'a ' + type(obj).__name__ if not kind else kind}")
    if len(found) > 1:
        raise IngestError(f"{det_dir} holds several detections JSON files {[p.name for _, p, _ in found]}; choose one "
                          f"with --set ingest.detections_json=NAME")
    if found:
        return found[0]
    if wanted == "auto" and (det_dir / "semantic").is_dir() and not cands:
        raise IngestError(f"{det_dir} has semantic/ but neither instance/ (the png_pair format) nor a COCO detections "
                          f"JSON; the folder has: {present} (docs/detector_formats.md)")
    if wanted == "auto":
        return "", None, None
    raise IngestError(f"ingest.detections_format={wanted}: no {wanted} JSON in {det_dir}; the folder has: {present}")


def categories_of(obj: Any) -> dict[int, str]:
    cats = obj.get("categories") if isinstance(obj, dict) else None
    if not isinstance(cats, list):
        return {}
    try:
        return {int(c["id"]): str(c["name"]) for c in cats}
    except (KeyError, TypeError, ValueError):
        return {}


def image_stamps(images: list, where: str,
                 stamp_unit: StampUnit = "auto") -> dict[int, tuple[int, int | None, int | None]]:
    """COCO images list -> {image id: (stamp_ns from the file name, height, width)}."""
    out = {}
    for n, img in enumerate(images):
        try:
            out[int(img["id"])] = (stamp_from_name(Path(str(img["file_name"])).stem, stamp_unit),
                                   int(img["height"]) if "height" in img else None,
                                   int(img["width"]) if "width" in img else None)
        except (KeyError, TypeError, ValueError) as err:
            raise IngestError(f"{where}: images[{n}] needs an id and a file_name named by the frame's stamp "
                              f"(like rgb/<stamp_ns>.png): {err}") from err
    return out


# -- the formats ------------------------------------------------------------------------------------

Count = Callable[[str, int], None]


def panoptic_ids(png: np.ndarray) -> np.ndarray:
    """[H, W, 3] RGB -> [H, W] segment id R + 256 G + 256^2 B."""
    p = png.astype(np.int64)
    return p[..., 0] + 256 * p[..., 1] + 65536 * p[..., 2]


def read_panoptic_png(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise UnreadableLabels(f"panoptic PNG {path} is {'not a readable PNG' if path.is_file() else 'missing'}")
    if img.ndim != 3 or img.shape[2] < 3 or img.dtype != np.uint8:
        raise IngestError(f"panoptic PNG {path}: expected 8-bit RGB (id = R + 256 G + 256^2 B), got {img.dtype} "
                          f"{img.shape}")
    return panoptic_ids(img[:, :, 2::-1])


class CocoPanoptic:
    """Per frame stamp: the annotation (file_name, segments_info)."""

    def __init__(self, path: Path, obj: dict, stamp_unit: StampUnit = "auto"):
        self.path, self.folder = path, path.with_suffix("")
        self.categories = categories_of(obj)
        self.by_stamp: dict[int, dict] = {}
        images = image_stamps(obj["images"], str(path), stamp_unit) if isinstance(obj.get("images"), list) else {}
        for n, ann in enumerate(obj["annotations"]):
            if not isinstance(ann, dict) or not isinstance(ann.get("segments_info"), list) or "file_name" not in ann:
                raise IngestError(f"{path}: annotations[{n}] needs file_name and a segments_info list")
            try:
                stamp = stamp_from_name(Path(str(ann["file_name"])).stem, stamp_unit)
            except IngestError:
                if ann.get("image_id") in images:
                    stamp = images[ann["image_id"]][0]
                else:
                    raise IngestError(f"{path}: annotations[{n}]: file_name {ann['file_name']!r} is not named by a "
                                      f"stamp and image_id {ann.get('image_id')!r} is not in an images list") from None
            for m, s in enumerate(ann["segments_info"]):
                if not isinstance(s, dict) or "id" not in s or "category_id" not in s:
                    raise IngestError(f"{path}: annotations[{n}] ({ann['file_name']}) segments_info[{m}] needs id and "
                                      f"category_id; got {s!r}")
            self.by_stamp[stamp] = ann
        if not self.folder.is_dir():
            raise IngestError(f"{path}: the panoptic PNG folder {self.folder} (named like the JSON) does not exist")

    def categories_used(self) -> set[int]:
        return {int(s["category_id"]) for a in self.by_stamp.values() for s in a["segments_info"]}

    def labels(self, stamp: int, shape: tuple[int, int], cmap: ClassMapper, count: Count) -> FrameLabels:
        ann = self.by_stamp[stamp]
        png_path = self.folder / str(ann["file_name"])
        ids = read_panoptic_png(png_path)
        if ids.shape != shape:
            raise IngestError(f"panoptic PNG {png_path} is {ids.shape[1]}x{ids.shape[0]}; the frame is "
                              f"{shape[1]}x{shape[0]}")
        infos = ann["segments_info"]
        present, areas = np.unique(ids, return_counts=True)
        area_of = dict(zip(present.tolist(), areas.tolist()))
        things = [s for s in infos if cmap(s["category_id"]) in THING_IDS]
        keep_ids = all(1 <= int(s["id"]) <= 65535 for s in things)
        if not keep_ids:
            count("panoptic_segment_ids_renumbered", len(things))
        sem = np.full(shape, VOID, np.uint8)
        inst = np.zeros(shape, np.uint16)
        lut_ids, lut_sem, lut_inst = [], [], []
        segments = []
        listed = set()
        for n, s in enumerate(infos):
            sid, klass = int(s["id"]), cmap(s["category_id"])
            listed.add(sid)
            if sid == 0 or sid not in area_of:
                count("segments_missing_in_png", 1)
                continue
            out_id = 0
            if klass in THING_IDS:
                out_id = sid if keep_ids else len(segments) + 1
                score = s.get("score")
                if score is None:
                    count("segments_without_score_set_to_1", 1)
                    score = 1.0
                segments.append((out_id, klass, min(max(float(score), 0.0), 1.0), int(area_of[sid])))
            lut_ids.append(sid)
            lut_sem.append(klass)
            lut_inst.append(out_id)
        unlisted = [i for i in present.tolist() if i != 0 and i not in listed]
        if unlisted:
            count("panoptic_pixels_without_segment_info", int(sum(area_of[i] for i in unlisted)))
        if lut_ids:
            order = np.argsort(lut_ids)
            keys = np.array(lut_ids)[order]
            pos = np.clip(np.searchsorted(keys, ids), 0, len(keys) - 1)
            hit = keys[pos] == ids
            sem[hit] = np.array(lut_sem, np.uint8)[order][pos[hit]]
            inst[hit] = np.array(lut_inst, np.uint16)[order][pos[hit]]
        return FrameLabels(sem, inst, sorted(segments))


class CocoInstances:
    """Per frame stamp: its results; stamps from an images list (in the JSON or images.json beside it) or,
    without one, from the image_id itself (read like a file name, by ingest.stamp_unit)."""

    def __init__(self, path: Path, obj: Any, semantic_dir: Path, stamp_unit: StampUnit = "auto"):
        self.path, self.semantic_dir = path, semantic_dir
        results = obj if isinstance(obj, list) else obj["annotations"]
        self.categories = categories_of(obj)
        images: dict[int, tuple[int, int | None, int | None]] = {}
        self.images_from = ""
        if isinstance(obj, dict) and isinstance(obj.get("images"), list):
            images, self.images_from = image_stamps(obj["images"], str(path), stamp_unit), str(path)
        elif (path.parent / IMAGES_JSON).is_file():
            side = read_json(path.parent / IMAGES_JSON)
            if not isinstance(side, dict) or not isinstance(side.get("images"), list):
                raise IngestError(f"{path.parent / IMAGES_JSON}: expected a COCO JSON with an images list")
            images = image_stamps(side["images"], str(path.parent / IMAGES_JSON), stamp_unit)
            self.images_from = str(path.parent / IMAGES_JSON)
            self.categories = self.categories or categories_of(side)
        self.by_stamp: dict[int, list[tuple[int, dict]]] = {}
        self.sizes: dict[int, tuple[int | None, int | None]] = {}
        for stamp, h, w in images.values():
            self.by_stamp.setdefault(stamp, [])
            self.sizes[stamp] = (h, w)
        for n, r in enumerate(results):
            if not isinstance(r, dict) or not all(k in r for k in ("image_id", "category_id", "segmentation")):
                raise IngestError(f"{path}: result [{n}] needs image_id, category_id and segmentation; got "
                                  f"{sorted(r) if isinstance(r, dict) else r!r}")
            if images:
                if r["image_id"] not in images:
                    raise IngestError(f"{path}: result [{n}] has image_id {r['image_id']!r}, which is not in the "
                                      f"images list of {self.images_from} ({len(images)} images)")
                stamp = images[r["image_id"]][0]
            else:
                try:
                    stamp = stamp_from_name(str(r["image_id"]), stamp_unit)
                except IngestError:
                    raise IngestError(f"{path}: result [{n}] has image_id {r['image_id']!r}, and there is no images "
                                      f"list (in the JSON or {IMAGES_JSON} beside it) to find its frame; without "
                                      f"one, image_id must be the frame's stamp") from None
            self.by_stamp.setdefault(stamp, []).append((n, r))

    def categories_used(self) -> set[int]:
        return {int(r["category_id"]) for rs in self.by_stamp.values() for _, r in rs}

    def labels(self, stamp: int, shape: tuple[int, int], cmap: ClassMapper, count: Count,
               semantic_png: Path | None) -> FrameLabels:
        h, w = shape
        if semantic_png is not None:
            raw_sem = cv2.imread(str(semantic_png), cv2.IMREAD_UNCHANGED)
            if raw_sem is None:
                raise UnreadableLabels(f"detector semantic PNG {semantic_png} is not a readable PNG")
            if raw_sem.ndim != 2 or raw_sem.dtype != np.uint8:
                raise IngestError(f"detector semantic PNG {semantic_png} is not a readable 8-bit single-channel PNG")
            if raw_sem.shape != shape:
                raise IngestError(f"detector semantic PNG {semantic_png} is {raw_sem.shape[1]}x{raw_sem.shape[0]}; the "
                                  f"frame is {w}x{h}")
            sem = cmap.lut(raw_sem)
            things = np.isin(sem, THING_IDS)
            sem[things] = VOID  # thing pixels come from the masks; one that no mask covers stays unlabelled
        else:
            sem = np.full(shape, VOID, np.uint8)
            things = np.zeros(shape, bool)
        inst = np.zeros(shape, np.uint16)
        results = self.by_stamp.get(stamp, [])
        masks = []
        for k, (n, r) in enumerate(results, start=1):
            try:
                m = coco.decode(r["segmentation"], h, w)
            except ValueError as err:
                raise IngestError(f"{self.path}: result [{n}] (image_id {r['image_id']}): {err}") from None
            score = r.get("score")
            if score is None:
                count("segments_without_score_set_to_1", 1)
                score = 1.0
            masks.append((k, cmap(r["category_id"]), min(max(float(score), 0.0), 1.0), m))
        # higher score painted last wins; equal scores keep file order (later wins)
        for k, klass, score, m in sorted(masks, key=lambda t: t[2]):
            sem[m] = klass
            inst[m] = k if klass in THING_IDS else 0
            things &= ~m
        if things.any():
            count("semantic_thing_pixels_without_mask_set_to_void", int(things.sum()))
        segments = []
        for k, klass, score, _ in masks:
            if klass not in THING_IDS:
                continue
            area = int((inst == k).sum())
            if area == 0:
                count("segments_hidden_by_higher_scores", 1)
                continue
            segments.append((k, klass, score, area))
        return FrameLabels(sem, inst, segments)


def match_stamps(frame_stamps: np.ndarray, stamps: list[int], tol_ns: int) -> np.ndarray:
    """For each frame, the index into sorted `stamps` within tol, else -1."""
    if not stamps:
        return np.full(len(frame_stamps), -1)
    return pair_nearest(np.asarray(frame_stamps, np.int64), np.array(sorted(stamps), np.int64), tol_ns)
