"""Pictures of an evaluation: cumulative error curves per method and a top view of positions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slamreloc.io.outputs import atomic_file, marked_file
from slamreloc.types import Frame

# the PNG text chunk that marks a plot `evaluate` wrote (and may replace)
PLOT_SOFTWARE = "slamreloc evaluate"
PLOT_FILE = marked_file(b"\x89PNG", PLOT_SOFTWARE.encode(), "a PNG plot slamreloc wrote")


def plot_evaluation(path: Path, results_by_method: dict, frames: list[Frame]) -> None:
    """A PNG at `path` (marked as slamreloc's: `PLOT_FILE`); results_by_method: method -> list
    of evaluate.QueryResult (same frame order)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    for method, results in results_by_method.items():
        t = np.sort([100 * r.translation_error_m for r in results])
        r = np.sort([r.rotation_error_deg for r in results])
        frac = np.arange(1, len(t) + 1) / max(len(t), 1)
        axes[0].step(t, frac, where="post", label=method)
        axes[1].step(r, frac, where="post", label=method)
        est = np.array([q.world_from_cam.translation for q in results if q.world_from_cam])
        if len(est):
            axes[2].scatter(est[:, 0], est[:, 1], s=6, label=f"{method} estimate")
    gt = np.array([f.world_from_cam.translation for f in frames if f.world_from_cam])
    axes[2].plot(gt[:, 0], gt[:, 1], "k-", lw=1, label="ground truth")
    lo, hi = gt[:, :2].min(0) - 0.5, gt[:, :2].max(0) + 0.5  # gross failures fall outside
    axes[2].set_xlim(lo[0], hi[0])
    axes[2].set_ylim(lo[1], hi[1])
    axes[0].set(xlim=(0, 20), ylim=(0, 1), xlabel="translation error (cm)",
                ylabel="fraction of queries", title="translation")
    axes[1].set(xlim=(0, 10), ylim=(0, 1), xlabel="rotation error (deg)", title="rotation")
    axes[2].set(xlabel="x (m)", ylabel="y (m)", title="top view (world x-y), +-0.5 m around truth")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(loc="lower right" if ax is not axes[2] else "best", fontsize=8)
    fig.tight_layout()
    try:
        with atomic_file(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png", metadata={"Software": PLOT_SOFTWARE})
    finally:
        plt.close(fig)
