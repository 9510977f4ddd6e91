import numpy as np

from ds3d.image2d.crops import crop_region, working_crops
from ds3d.image2d.params import EstimatorParams


def _image(height: int = 80, width: int = 120) -> np.ndarray:
    """No black pixel of its own."""
    rng = np.random.default_rng(0)
    return rng.integers(1, 256, (height, width, 3), dtype=np.uint8)


def test_a_box_crop_reaches_past_the_image_only_where_its_box_does():
    plain = EstimatorParams(box_margin=0.35, box_to_extent=1.0)
    wide = EstimatorParams(box_margin=0.35, box_to_extent=1.0, beyond_edge=0.2)
    inside = (5.0, 10.0, 45.0, 70.0)  # extent 60 px: a margin of 21 px
    (x0, y0, x1, y1), extent = crop_region(inside, 120, 80, plain)
    assert extent == 60 and (x0, y0, x1, y1) == (0, 0, 66, 80)  # the image's edges
    assert crop_region(inside, 120, 80, wide)[0] == (0, 0, 66, 80)
    past_left = (-10.0, 10.0, 30.0, 70.0)
    assert crop_region(past_left, 120, 80, plain)[0] == (0, 0, 51, 80)
    # past the left edge the margin stops at 12 px (0.2 of 60), the other sides at the image's
    assert crop_region(past_left, 120, 80, wide)[0] == (-12, 0, 51, 80)


def test_a_crop_past_the_image_is_black_there_and_the_image_elsewhere():
    image = _image()
    params = EstimatorParams(box_margin=0.35, box_to_extent=1.0, beyond_edge=0.2)
    (crop,) = working_crops([image], [(-10.0, 10.0, 30.0, 70.0)], params)
    assert (crop.x0, crop.y0) == (-12, 0) and crop.image.shape == (80, 63, 3)
    assert (crop.image[:, 12:] == image[:, :51]).all() and crop.image[:, :12].max() == 0


def test_a_whole_image_is_its_own_crop_whatever_beyond_edge():
    image = _image()
    params = EstimatorParams(image_to_extent=1.2, beyond_edge=0.3)
    (crop,) = working_crops([image], None, params)
    assert (crop.x0, crop.y0) == (0, 0) and crop.image is image
    assert crop.base == params.canonical_extent / 100  # a person of 120 px / 1.2
