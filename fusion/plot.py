"""Pictures of a fused run: trajectories with covariance ellipses, and errors over time."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from skyfix.errors import InputError
from skyfix.fusion.replay import ReplayResult, horizontal_errors_m

_CHI2_2DOF_95 = 5.991464547107979  # scipy.stats.chi2.ppf(0.95, 2)


def ellipse_points(cov_m2: np.ndarray, n_sigma: float, n: int = 48) -> np.ndarray:
    """(n, 2) outline (m) of the ellipse x^T C^-1 x = n_sigma^2 (C the 2x2 covariance ``cov_m2``, m2).

    Example (sigmas 2 m east, 1 m north; the 2-sigma ellipse reaches 4 m and 2 m):
        >>> np.abs(ellipse_points(np.diag([4.0, 1.0]), 2.0, n=5)).max(axis=0)
        array([4., 2.])
    """
    vals, vecs = np.linalg.eigh(cov_m2)
    ang = np.linspace(0.0, 2.0 * np.pi, n)
    circle = np.stack([np.cos(ang), np.sin(ang)])
    return (vecs @ (np.sqrt(np.maximum(vals, 0.0))[:, None] * circle)).T * n_sigma


def plot_replay(result: ReplayResult, path: str | Path, *, drones: list[str] | None = None,
                ellipse_every_s: float = 10.0) -> Path:
    """Write a PNG: east/north map (truth, GNSS, fused, 95 % ellipses; GNSS lost or rejected in red)
    and, when the log has truth, horizontal error against the 95 % bound per drone."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    unknown = sorted(set(drones or ()) - set(result.fused))
    if unknown:
        raise InputError(f"drones {unknown} are not in the replay (drones: {sorted(result.fused)})")
    ids = list(drones or sorted(result.fused))
    has_truth = any(result.truth_enu_m.get(d) for d in ids)
    fig = plt.figure(figsize=(15, 8) if has_truth else (10, 8))
    ax = fig.add_subplot(1, 2, 1) if has_truth else fig.add_subplot(1, 1, 1)
    colours = plt.get_cmap("tab10")
    scale = np.sqrt(_CHI2_2DOF_95)
    for i, drone in enumerate(ids):
        c = colours(i % 10)
        t, enu, cov = result.fused[drone].arrays()
        truth = result.truth_enu_m.get(drone)
        if truth:
            tp = np.array([p for _, p in truth])
            ax.plot(tp[:, 0], tp[:, 1], color="k", lw=0.8, ls="--", alpha=0.6,
                    label="truth" if i == 0 else None)
        gnss = result.gnss_enu_m.get(drone)
        if gnss:
            gp = np.array([p for _, p in gnss])
            ax.plot(gp[:, 0], gp[:, 1], ".", color=c, ms=2, alpha=0.35, label=f"{drone} GNSS")
        ax.plot(enu[:, 0], enu[:, 1], color=c, lw=1.4, label=f"{drone} fused")
        bad = np.array([s in ("lost", "rejected") for s in result.fused[drone].gnss_state])
        if bad.any():
            ax.plot(np.where(bad, enu[:, 0], np.nan), np.where(bad, enu[:, 1], np.nan), color="red", lw=2.2,
                    label="fused, GNSS lost/rejected" if i == 0 else None)
        next_t = -np.inf
        for k in range(len(t)):
            if t[k] >= next_t:
                outline = ellipse_points(cov[k, :2, :2], scale) + enu[k, :2]
                ax.plot(outline[:, 0], outline[:, 1], color=c, lw=0.7, alpha=0.8)
                next_t = t[k] + ellipse_every_s
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)
    ax.set_title(f"fused tracks, 95 % ellipses every {ellipse_every_s:g} s\n"
                 f"origin {result.origin[0]:.6f}, {result.origin[1]:.6f}")
    if has_truth:
        rows = [d for d in ids if result.truth_enu_m.get(d)]
        for j, drone in enumerate(rows):
            axe = fig.add_subplot(len(rows), 2, 2 * j + 2)
            t, _, cov = result.fused[drone].arrays()
            err = horizontal_errors_m(result.fused[drone], result.truth_enu_m[drone])
            bound = scale * np.sqrt(np.linalg.eigvalsh(cov[:, :2, :2])[:, -1])
            axe.plot(t, err, color=colours(ids.index(drone) % 10), lw=0.9, label="horizontal error")
            axe.plot(t, bound, color="grey", lw=0.9, ls="--", label="95 % bound (major axis)")
            bad = np.array([s in ("lost", "rejected") for s in result.fused[drone].gnss_state])
            if bad.any():
                axe.fill_between(t, 0, max(err.max(), bound.max()), where=bad, color="red", alpha=0.12,
                                 label="GNSS lost/rejected")
            axe.set_ylabel(f"{drone} error (m)")
            axe.grid(alpha=0.3)
            if j == 0:
                axe.legend(loc="upper right", fontsize=8)
                axe.set_title("horizontal error against truth")
            if j == len(rows) - 1:
                axe.set_xlabel("time (s)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
