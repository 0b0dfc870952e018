"""Pictures of fitted materials (paper figure 14 style) and of fit traces."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.io import atomic_path
from glsldiff.core.plotting import pyplot


def depth_slices(path: str | os.PathLike, kappa: NDArray, mu: NDArray, h: float,
                 depths: Sequence[int] | None = None, truth: tuple[NDArray, NDArray] | None = None) -> Path:
    """PNG of kappa (mm) and mu (mm^-1) at several depths (z-slices), channel 1 (green);
    with ``truth`` the true volume's slices are drawn in the row above each fitted row."""
    plt = pyplot()

    nz = kappa.shape[0]
    if depths is None:
        depths = sorted({1, nz // 4, nz // 2, (3 * nz) // 4, nz - 2})
    rows = [("kappa (mm)", kappa[..., 1], None), ("mu (1/mm)", mu[..., 1], None)]
    if truth is not None:
        rows = [("true kappa (mm)", truth[0][..., 1], 0), ("fitted kappa (mm)", kappa[..., 1], 0),
                ("true mu (1/mm)", truth[1][..., 1], 1), ("fitted mu (1/mm)", mu[..., 1], 1)]
    fig, axes = plt.subplots(len(rows), len(depths), figsize=(2.2 * len(depths), 2.1 * len(rows)),
                             squeeze=False)
    for r, (label, vol, group) in enumerate(rows):
        pair = [v for (_, v, g) in rows if g == group] if group is not None else [vol]
        inner = np.concatenate([v[1:-1, 1:-1, 1:-1].ravel() for v in pair])
        lo, hi = float(np.percentile(inner, 1)), float(np.percentile(inner, 99))
        for c, z in enumerate(depths):
            ax = axes[r, c]
            im = ax.imshow(vol[z], vmin=lo, vmax=hi, cmap="viridis", origin="lower")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(f"depth {z * h:.1f} mm", fontsize=8)
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
        fig.colorbar(im, ax=axes[r, :].tolist(), shrink=0.8)
    with atomic_path(path, ".png") as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
    return Path(path)
