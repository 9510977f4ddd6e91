"""Pose metrics as pure functions over batches (numpy or torch in, torch out).

3D (mm): mpjpe (no alignment beyond what the caller did), rigid_error (the paper's "3D pose
error": rotation + translation, no scale), pa_mpjpe (Procrustes with scale). 2D (px): pck and
the mean pixel error. Probabilities: their reliability bins and expected calibration error.
"""

from __future__ import annotations

import torch

from ds3d.skeleton import L_HIP, L_SHOULDER, R_HIP, R_SHOULDER


def _t(value) -> torch.Tensor:
    return torch.as_tensor(value).double()


def mpjpe(pred, gt) -> torch.Tensor:
    """Mean per-joint position error. pred, gt: (N, J, D). Returns (N,) in their unit."""
    return (_t(pred) - _t(gt)).norm(dim=-1).mean(-1)


def align(pred, gt, scale: bool) -> torch.Tensor:
    """The similarity (scale=True) or rigid (scale=False) transform of pred that best fits gt in
    least squares (Kabsch/Umeyama, reflections excluded). pred, gt: (N, J, 3). Returns (N, J, 3)."""
    pred, gt = _t(pred), _t(gt)
    mu_p, mu_g = pred.mean(-2, keepdim=True), gt.mean(-2, keepdim=True)
    p, g = pred - mu_p, gt - mu_g
    u, sigma, vh = torch.linalg.svd(p.transpose(-1, -2) @ g)
    d = torch.sign(torch.linalg.det(u @ vh))  # -1 where the best fit would be a reflection
    fix = torch.ones_like(sigma)
    fix[..., -1] = d
    rotation = u @ torch.diag_embed(fix) @ vh  # applied as p @ rotation
    s = (sigma * fix).sum(-1) / (p**2).sum((-1, -2)) if scale else torch.ones_like(d)
    return s[..., None, None] * p @ rotation + mu_g


def rigid_error(pred, gt) -> torch.Tensor:
    """The paper's 3D pose error: mean joint distance after a rigid alignment. (N,) mm."""
    return mpjpe(align(pred, gt, scale=False), gt)


def pa_mpjpe(pred, gt) -> torch.Tensor:
    """MPJPE after Procrustes alignment with scale. (N,) mm."""
    return mpjpe(align(pred, gt, scale=True), gt)


def torso_diameter(gt, placed=None) -> torch.Tensor:
    """LSP's PCK reference: the distance between opposite shoulder and hip, (N,) px. gt:
    (N, 14, 2). The mean of the two diagonals, which is defined when the torso is foreshortened;
    placed: None, or (N, 14) bool, the joints annotated: the mean of the diagonals whose ends
    both are (NaN where neither's are)."""
    gt = _t(gt)
    diagonals = torch.stack(
        [
            (gt[:, R_SHOULDER] - gt[:, L_HIP]).norm(dim=-1),
            (gt[:, L_SHOULDER] - gt[:, R_HIP]).norm(dim=-1),
        ],
        -1,
    )
    if placed is None:
        return diagonals.mean(-1)
    placed = _t(placed).bool()
    whole = torch.stack(
        [placed[:, R_SHOULDER] & placed[:, L_HIP], placed[:, L_SHOULDER] & placed[:, R_HIP]], -1
    )
    return (diagonals * whole).sum(-1) / whole.sum(-1)


def pck(pred, gt, visible=None, threshold: float = 0.2, reference=None) -> torch.Tensor:
    """Per-joint PCK: the fraction of visible joints within threshold * the reference length.
    pred, gt: (N, 14, 2) px; visible: (N, 14) bool or None; reference: (N,) px, by default
    torso_diameter(gt). Returns (14,) in [0, 1]."""
    pred, gt = _t(pred), _t(gt)
    mask = torch.ones(gt.shape[:2], dtype=torch.bool) if visible is None else _t(visible).bool()
    length = torso_diameter(gt) if reference is None else _t(reference)
    correct = (pred - gt).norm(dim=-1) <= threshold * length[:, None]
    return (correct & mask).sum(0).double() / mask.sum(0).clamp_min(1)


def pixel_error(pred, gt, visible=None) -> torch.Tensor:
    """Mean distance (px) over visible joints, per joint: (14,)."""
    pred, gt = _t(pred), _t(gt)
    mask = torch.ones(gt.shape[:2], dtype=torch.bool) if visible is None else _t(visible).bool()
    distance = (pred - gt).norm(dim=-1) * mask
    return distance.sum(0) / mask.sum(0).clamp_min(1)


def reliability(confidence: torch.Tensor, correct: torch.Tensor, bins: int = 10) -> list[dict]:
    """The reliability diagram's bins of equal width over [0, 1]: for each bin holding any
    confidence, {low, high, count, confidence: the mean confidence, accuracy: the fraction
    right}. confidence, correct: any shape, alike."""
    conf, right = confidence.flatten().double(), correct.flatten().double()
    index = (conf * bins).long().clamp(0, bins - 1)
    rows = []
    for k in range(bins):
        inside = index == k
        n = int(inside.sum())
        if n:
            rows.append(
                {
                    "low": k / bins,
                    "high": (k + 1) / bins,
                    "count": n,
                    "confidence": round(float(conf[inside].mean()), 4),
                    "accuracy": round(float(right[inside].mean()), 4),
                }
            )
    return rows


def expected_calibration_error(
    confidence: torch.Tensor, correct: torch.Tensor, bins: int = 10
) -> float:
    """ECE: the mean over the reliability bins, weighted by their counts, of |mean confidence -
    fraction right|; 0 for confidences that are exactly as often right as they say."""
    rows = reliability(confidence, correct, bins)
    total = sum(r["count"] for r in rows)
    return sum(r["count"] * abs(r["confidence"] - r["accuracy"]) for r in rows) / max(total, 1)
