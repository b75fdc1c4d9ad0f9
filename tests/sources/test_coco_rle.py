import numpy as np
import pytest

from sources import coco


def test_documented_example():
    m = np.array([[0, 1], [0, 1]], bool)
    assert coco.mask_to_counts(m) == [2, 2]
    assert coco.encode(m) == {"size": [2, 2], "counts": "22"}


@pytest.mark.parametrize("seed", range(5))
def test_round_trip_random_masks(seed):
    rng = np.random.default_rng(seed)
    m = rng.random((37, 53)) < rng.uniform(0.05, 0.95)
    m[5:30, 10:40] = seed % 2 == 0
    assert np.array_equal(coco.decode(coco.encode(m)), m)
    assert np.array_equal(coco.decode({"size": [37, 53], "counts": coco.mask_to_counts(m)}), m)


def test_large_counts_and_first_pixel_set():
    m = np.zeros((300, 400), bool)
    m[0, 0] = True
    m[100:250, 3:390] = True
    assert np.array_equal(coco.decode(coco.encode(m)), m)


def test_bad_rle_is_a_clear_error():
    with pytest.raises(ValueError, match="sum to"):
        coco.decode({"size": [2, 2], "counts": [1, 1]})
    with pytest.raises(ValueError, match="not a COCO RLE"):
        coco.decode({"counts": "22"})


def test_hand_written_codec_agrees_with_pycocotools_on_the_synthetic_annotations(tiny_raw):
    import json

    from pycocotools import mask as cocomask

    ann = json.loads((tiny_raw / "annotations.json").read_text())
    assert ann["annotations"]
    for a in ann["annotations"]:
        rle = a["segmentation"]
        ours = coco.decode(rle)
        theirs = cocomask.decode({"size": rle["size"], "counts": rle["counts"].encode()}).astype(bool)
        assert np.array_equal(ours, theirs)
        assert cocomask.encode(np.asfortranarray(ours.astype(np.uint8)))["counts"].decode() == rle["counts"]
        assert int(cocomask.area({"size": rle["size"], "counts": rle["counts"].encode()})) == a["area"]
