"""Person boxes given by users: one check for the CLI, the Python API and the service."""

import numpy as np
import pytest

from ds3d.boxes import checked_box
from ds3d.errors import InvalidBox


def test_a_box_inside_or_overlapping_the_image_is_kept():
    assert checked_box([10, 20, 110, 220], 200, 300).tolist() == [10, 20, 110, 220]
    assert checked_box(np.array([-50, -50, 10, 10]), 200, 300).dtype == np.float32


@pytest.mark.parametrize(
    ("box", "why"),
    [
        ([110, 20, 10, 220], "no area"),  # reversed corners
        ([10, 20, 10, 220], "no area"),  # zero width
        ([300, 20, 400, 220], "outside the 200x300 image"),
        ([-90, -90, -10, -10], "outside"),
        ([1, 2, 3], "four numbers"),
        (["a", 2, 3, 4], "four numbers"),
        ([0, 0, float("nan"), 5], "NaN or infinite"),
    ],
)
def test_a_box_the_image_cannot_hold_is_refused_with_the_reason(box, why):
    with pytest.raises(InvalidBox, match=why):
        checked_box(box, 200, 300)
