"""What users give the library, checked once where it enters (ds3d.inputs): person boxes, images
and their options."""

import numpy as np
import pytest

from ds3d.errors import InvalidBox, InvalidImage, InvalidPose
from ds3d.inputs import (
    MAX_ASPECT_RATIO,
    MAX_BOX_SCALE,
    MIN_BOX_PX,
    checked_box,
    image_input,
    image_inputs,
)


def test_a_box_inside_or_overlapping_the_image_is_kept():
    assert checked_box([10, 20, 110, 220], 200, 300).tolist() == [10, 20, 110, 220]
    assert checked_box(np.array([-50, -50, 10, 10]), 200, 300).dtype == np.float32
    largest = MAX_BOX_SCALE * 300
    assert checked_box([-100, -50, largest - 100, 250], 200, 300)[2] == largest - 100


def test_a_box_under_a_pixel_is_widened_about_its_centre():
    """A sub-pixel box (a fraction of the image sent as pixels, say) is taken as MIN_BOX_PX a
    side about its centre, the size the 2D stage can scale; a wider side stays as it is."""
    box = checked_box([10, 20, 10.001, 60], 200, 300)
    assert box.tolist() == pytest.approx(
        [10.0005 - MIN_BOX_PX / 2, 20, 10.0005 + MIN_BOX_PX / 2, 60]
    )


@pytest.mark.parametrize(
    ("box", "why"),
    [
        ([110, 20, 10, 220], "no area"),  # reversed corners
        ([10, 20, 10, 220], "no area"),  # zero width
        ([300, 20, 400, 220], "outside the 200x300 image"),
        ([-90, -90, -10, -10], "outside"),
        ([0, 0, 100, MAX_BOX_SCALE * 300 + 1], "over 4 times the size of the 200x300 image"),
        ([1, 2, 3], "four numbers"),
        (["a", 2, 3, 4], "four numbers"),
        ([0, 0, float("nan"), 5], "NaN or infinite"),
    ],
)
def test_a_box_the_image_cannot_hold_is_refused_with_the_reason(box, why):
    with pytest.raises(InvalidBox, match=why):
        checked_box(box, 200, 300)


def test_an_image_is_checked_once_with_its_options():
    image = np.zeros((300, 200, 3), np.uint8)
    item = image_input(image, [10, 20, 110, 220], focal_px=800, people="all", min_score=0.3)
    assert item.bbox.tolist() == [10, 20, 110, 220] and item.focal_px == 800.0
    assert (item.people, item.min_score, item.intrinsics) == ("all", 0.3, None)
    with pytest.raises(InvalidImage, match="uint8"):
        image_input(image.astype(np.float32))
    with pytest.raises(InvalidBox):
        image_input(image, [300, 20, 400, 220])
    with pytest.raises(InvalidPose, match="focal_px"):
        image_input(image, focal_px=0.0)
    with pytest.raises(ValueError, match="people"):
        image_input(image, people="some")
    with pytest.raises(ValueError, match="min_score"):
        image_input(image, min_score=float("nan"))


def test_an_image_too_elongated_to_search_is_refused_unless_a_box_says_where_to_look():
    strip = np.zeros((10, int(10 * MAX_ASPECT_RATIO) + 1, 3), np.uint8)
    with pytest.raises(InvalidImage, match="max_aspect_ratio"):
        image_input(strip)
    assert image_input(strip, [0, 0, 20, 10]).bbox is not None
    assert image_input(strip[:, : int(10 * MAX_ASPECT_RATIO)]).bbox is None


def test_options_are_given_once_for_all_images_or_once_per_image():
    images = [np.zeros((100, 80, 3), np.uint8)] * 3
    k = np.array([[500, 0, 40], [0, 500, 50], [0, 0, 1]], np.float32)
    items = image_inputs(images, [None, [0, 0, 40, 90], None], k, people=["best", "all", "best"])
    assert [item.bbox is None for item in items] == [True, False, True]
    assert all(np.array_equal(item.intrinsics, k) for item in items)
    assert [item.people for item in items] == ["best", "all", "best"]
    mixed = image_inputs(images, intrinsics=[None, k, None])
    assert [item.intrinsics is None for item in mixed] == [True, False, True]
    with pytest.raises(ValueError, match="2 values of people for 3 images"):
        image_inputs(images, people=["best", "all"])
