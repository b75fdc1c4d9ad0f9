"""COCO masks through pycocotools: the documented example, round trips, polygons and clear errors."""
import json

import numpy as np
import pytest
from pycocotools import mask as cocomask

from pipeline.images import read_label
from sources import coco


def test_documented_example():
    m = np.array([[0, 1], [0, 1]], bool)
    assert coco.encode(m) == {"size": [2, 2], "counts": "22"}
    assert np.array_equal(coco.decode({"size": [2, 2], "counts": [2, 2]}), m)


@pytest.mark.parametrize("seed", range(5))
def test_round_trip_random_masks(seed):
    rng = np.random.default_rng(seed)
    m = rng.random((37, 53)) < rng.uniform(0.05, 0.95)
    m[5:30, 10:40] = seed % 2 == 0
    assert np.array_equal(coco.decode(coco.encode(m)), m)


def test_large_counts_and_first_pixel_set():
    m = np.zeros((300, 400), bool)
    m[0, 0] = True
    m[100:250, 3:390] = True
    assert np.array_equal(coco.decode(coco.encode(m)), m)


def test_synthetic_annotations_decode_to_the_ground_truth_masks_and_encode_back(tiny_raw):
    ann = json.loads((tiny_raw / "annotations.json").read_text())
    assert ann["annotations"]
    images = {img["id"]: img for img in ann["images"]}
    for a in ann["annotations"]:
        stamp = images[a["image_id"]]["stamp_ns"]
        gt = read_label(tiny_raw / "gt" / "instance" / f"{stamp}.png", "gt") == a["instance_id"]
        m = coco.decode(a["segmentation"], *gt.shape)
        assert np.array_equal(m, gt) and m.sum() == a["area"]
        assert coco.encode(m) == a["segmentation"]
        # the uncompressed form of the same mask decodes to it too
        counts = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], m.ravel(order="F"), [2]]))), prepend=0)
        assert np.array_equal(coco.decode({"size": list(gt.shape), "counts": [int(c) for c in counts]}), m)


def test_polygon_decodes_like_pycocotools():
    poly = [[2.0, 2.0, 17.0, 3.0, 15.0, 12.0, 4.0, 10.0]]
    m = coco.decode(poly, 16, 20)
    ref = cocomask.decode(cocomask.merge(cocomask.frPyObjects(poly, 16, 20))).astype(bool)
    assert np.array_equal(m, ref) and 100 < m.sum() < 160


@pytest.mark.parametrize("seg, message", [
    ({"size": [2, 2], "counts": [1, 1]}, "sum to 2, expected 2x2 = 4"),
    ({"counts": "22"}, "not a COCO RLE"),
    ({"size": [2, 2], "counts": "2"}, "does not describe a 2x2 mask"),
    ({"size": [2, 2], "counts": "2222"}, "does not describe a 2x2 mask"),
    ({"size": [2, 2], "counts": 7}, "string or a list"),
    ([[1.0, 2.0, 3.0]], "not a COCO polygon"),
    ("x", "not a COCO segmentation"),
])
def test_bad_coco_segmentation_is_a_clear_error(seg, message):
    with pytest.raises(ValueError, match=message):
        coco.decode(seg, 2, 2)


def test_rle_of_another_size_than_the_image_is_an_error():
    with pytest.raises(ValueError, match=r"RLE mask is 2x2 \(size \[h, w\]\) but the image is 3x2"):
        coco.decode({"size": [2, 2], "counts": "22"}, 3, 2)
