"""The batched symmetric eigensolver (ds3d.fit.eigen) against LAPACK's."""

from __future__ import annotations

import pytest
import torch

from ds3d.fit.eigen import jacobi_eigh


@pytest.mark.parametrize("n", [2, 3, 7, 42])
def test_jacobi_finds_lapacks_eigenvalues_and_an_orthonormal_basis(n):
    torch.manual_seed(n)
    a = torch.randn(6, n, n, dtype=torch.float64)
    a = a + a.transpose(1, 2)
    values, vectors = jacobi_eigh(a)
    torch.testing.assert_close(values, torch.linalg.eigh(a).eigenvalues, rtol=0, atol=1e-10)
    eye = torch.eye(n, dtype=a.dtype).expand_as(a)
    torch.testing.assert_close(vectors.transpose(1, 2) @ vectors, eye, rtol=0, atol=1e-10)
    torch.testing.assert_close((vectors * values[:, None]) @ vectors.transpose(1, 2), a)


def test_jacobi_resolves_a_pose_scatters_spread_of_variances_in_float32():
    """A scatter like the 3D fit's: 128 samples of 42 values whose spreads fall a thousandfold;
    the leading eigenvectors (the PCA basis) agree with LAPACK's in float64 up to sign."""
    torch.manual_seed(0)
    samples = torch.randn(8, 128, 42, dtype=torch.float64) * torch.logspace(2, -1, 42)
    scatter = samples.transpose(1, 2) @ samples
    expected = torch.linalg.eigh(scatter)
    values, vectors = jacobi_eigh(scatter.float())
    top = slice(-20, None)
    torch.testing.assert_close(
        values[:, top].double(), expected.eigenvalues[:, top], rtol=1e-4, atol=0
    )
    agreement = (vectors[:, :, top].double() * expected.eigenvectors[:, :, top]).sum(1).abs()
    assert float(agreement.min()) > 0.999


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
def test_on_cuda_the_pca_is_lapacks():
    """symmetric_eigh on a CUDA tensor (the Jacobi method there) against LAPACK's on the CPU."""
    from ds3d.fit.eigen import symmetric_eigh

    torch.manual_seed(0)
    samples = torch.randn(64, 128, 42) * torch.logspace(2, -1, 42)
    scatter = samples.transpose(1, 2) @ samples
    values, vectors = symmetric_eigh(scatter.cuda())
    expected = torch.linalg.eigh(scatter)
    assert values.is_cuda and vectors.is_cuda
    top = slice(-20, None)
    torch.testing.assert_close(
        values[:, top].cpu(), expected.eigenvalues[:, top], rtol=1e-4, atol=0
    )
    agreement = (vectors[:, :, top].cpu() * expected.eigenvectors[:, :, top]).sum(1).abs()
    assert float(agreement.min()) > 0.999
