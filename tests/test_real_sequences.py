"""The shared real sequences load (skipped when ../shared/data is absent)."""

import numpy as np
import pytest

from jsr.io.dataset import open_sequence

pytestmark = pytest.mark.real


@pytest.mark.parametrize(
    "name, frames, distorted",
    [("redkitchen300", 300, False), ("bonn_crowd200", 200, True), ("kitchen_box120", 120, False)],
)
def test_shared_sequence_loads(shared_data, name, frames, distorted):
    sequence = open_sequence(shared_data / name)
    assert len(sequence) == frames
    assert sequence.intrinsics.has_distortion == distorted
    assert sequence.groundtruth is not None and len(sequence.groundtruth[0]) >= frames
    for index in (0, frames // 2, frames - 1):
        frame = sequence[index]
        assert frame.color.shape == (480, 640, 3) and frame.depth.shape == (480, 640)
        valid = frame.depth[frame.depth > 0]
        assert valid.size > 0.5 * frame.depth.size
        assert 0.3 < np.median(valid) < 5.0  # metres, so depth_scale was applied
