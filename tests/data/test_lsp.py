"""LSP / LSPet readers: 1-based MATLAB pixels become 0-based, both visibility conventions
become True = visible. Synthetic .mat files, so no dataset is needed."""

import numpy as np
import pytest
import scipy.io

from ds3d.data.lsp import load_lsp, load_lspet
from ds3d.errors import DataFormatError


def test_lsp_converts_coordinates_and_inverted_flags(tmp_path):
    rng = np.random.default_rng(0)
    raw = np.zeros((3, 14, 2000))
    raw[:2] = rng.uniform(1, 150, (2, 14, 2000))
    raw[2] = rng.integers(0, 2, (14, 2000))  # LSP: 0 = visible
    scipy.io.savemat(tmp_path / "joints.mat", {"joints": raw})
    test = load_lsp(tmp_path, split="test")
    assert len(test) == 1000 and test.image_paths[0].name == "im1001.jpg"
    np.testing.assert_allclose(test.joints[0, 3], raw[:2, 3, 1000] - 1, rtol=1e-6)
    np.testing.assert_array_equal(test.visible, raw[2, :, 1000:].T == 0)
    train = load_lsp(tmp_path, split="train")
    assert train.image_paths[-1].name == "im1000.jpg" and train.joints.dtype == np.float32
    with pytest.raises(ValueError):
        load_lsp(tmp_path, split="val")


def test_lspet_converts_coordinates_and_flags(tmp_path):
    raw = np.zeros((14, 3, 5))
    raw[:, 0, :] = 11.0
    raw[:, 1, :] = 21.0
    raw[:, 2, :] = 1  # LSPet: 1 = visible
    raw[4, 2, 2] = 0
    scipy.io.savemat(tmp_path / "joints.mat", {"joints": raw})
    ann = load_lspet(tmp_path)
    assert len(ann) == 5 and ann.image_paths[4].name == "im00005.jpg"
    assert (ann.joints == np.array([10.0, 20.0], dtype=np.float32)).all()
    assert ann.visible.sum() == 5 * 14 - 1 and not ann.visible[2, 4]
    both = ann.concat(ann.subset([0]))
    assert len(both) == 6 and both.joints.shape == (6, 14, 2)


def test_bad_files_raise_data_format_error(tmp_path):
    with pytest.raises(DataFormatError):
        load_lsp(tmp_path)
    scipy.io.savemat(tmp_path / "joints.mat", {"joints": np.zeros((14, 3, 10))})
    with pytest.raises(DataFormatError):
        load_lsp(tmp_path)  # LSPet layout is not LSP's
