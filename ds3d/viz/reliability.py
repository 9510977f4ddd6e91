"""The reliability diagram of confidences: how often what was said to be right with
probability p was right, bin by bin (ds3d.confidence.reliability's rows)."""

from __future__ import annotations

from pathlib import Path


def plot_reliability(
    curves: dict[str, list[dict]],
    path: Path,
    title: str = "",
    right: str = "fraction of joints right",
) -> None:
    """One line per labelled set of reliability rows (the fraction right, named `right`, against
    the mean confidence, each bin a marker sized by its count) beside the diagonal of perfect
    calibration; a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    ax.plot([0, 1], [0, 1], color="0.6", ls="--", lw=1, label="calibrated")
    for label, rows in curves.items():
        total = sum(r["count"] for r in rows)
        sizes = [4 + 400 * r["count"] / total for r in rows]
        x, y = [r["confidence"] for r in rows], [r["accuracy"] for r in rows]
        (line,) = ax.plot(x, y, lw=1, label=label)
        ax.scatter(x, y, s=sizes, color=line.get_color())
    ax.set(xlim=(0, 1), ylim=(0, 1), xlabel="confidence", ylabel=right)
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
