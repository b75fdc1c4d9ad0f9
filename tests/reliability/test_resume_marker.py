"""A finished window is reused only when its marker is complete and made from the same payload."""
import pickle

from stages.nerf_fit import FINISHED, finished_window, payload_digest


def test_finished_window_needs_a_whole_marker_with_the_same_digest(tmp_path):
    payload = {"window_id": 0, "frames": {"frame_id": [1, 2]}, "out_dir": "/a", "resume_dir": "/b"}
    digest = payload_digest(payload)
    assert digest == payload_digest({**payload, "out_dir": "/elsewhere", "resume_dir": "/c"})  # paths aside
    assert digest != payload_digest({**payload, "frames": {"frame_id": [1, 3]}})
    folder = tmp_path / "window_000"
    assert finished_window(folder, digest) is None  # nothing there
    folder.mkdir()
    rows = {"poses": {"frame_id": [1, 2]}, "metrics": {"window_id": 0}}
    data = pickle.dumps({"digest": digest, "result": rows})
    (folder / FINISHED).write_bytes(data[: len(data) // 2])
    assert finished_window(folder, digest) is None  # cut short
    (folder / FINISHED).write_bytes(data)
    assert finished_window(folder, digest) == rows
    assert finished_window(folder, payload_digest({**payload, "window_id": 1})) is None  # other inputs
