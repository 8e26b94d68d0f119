"""What a pipeline run produced and why: ``report.json`` and the ``report.png`` summary."""

from __future__ import annotations

import json
import math
import os
import resource
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from skyfix.jsonfile import json_safe

__all__ = ["Report", "peak_memory_mib"]


def peak_memory_mib() -> float:
    """Peak resident memory of this process so far, MiB (Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@dataclass
class Report:
    """A pipeline run. Times in seconds, memory in MiB, lengths in metres unless named.

    ``models``: one dict per reconstructed model (see ``ModelGeoref.to_dict``), largest first.
    ``stage_seconds``: time of each stage when it ran (a resumed stage keeps its earlier
    time and is listed in ``resumed_stages``). ``warnings``: every user-facing warning.
    ``registered_two_view``: photos registered via a two-view model with one registered
    neighbour (photo, partner, inliers, distance from GPS). ``error``: why the run stopped.
    ``flying_height``: the model's camera height above its ground next to the photos' own
    relative altitude (see :mod:`skyfix.mapping.height_check`), with the readable ``line``.
    ``gps_lag``: the GPS time lag estimated on the largest model (seconds, RMS without and
    with it, whether it was removed; see :mod:`skyfix.mapping.gps_lag`).
    """

    photos_dir: str
    out_dir: str
    photos_found: int = 0
    photos_used: list[str] = field(default_factory=list)
    rejected: list[dict] = field(default_factory=list)
    without_gps: list[str] = field(default_factory=list)
    camera_groups: list[dict] = field(default_factory=list)
    isolated_by_gps: list[str] = field(default_factory=list)
    matching: str = ""
    registered: list[str] = field(default_factory=list)
    unregistered: list[str] = field(default_factory=list)
    registered_two_view: list[dict] = field(default_factory=list)
    models: list[dict] = field(default_factory=list)
    mean_reprojection_error_px: float = math.nan
    points: int = 0
    georeferenced: bool = False
    georef_rms_m: float = math.nan
    georef_rms_horizontal_m: float = math.nan
    crs_epsg: int | None = None
    gsd_cm: float = math.nan
    resolution_cm: float = math.nan
    dsm_resolution_m: float = math.nan
    covered_area_m2: float = 0.0
    height_datum: str = "AMSL (as recorded by the photos' GPS)"
    flying_height: dict = field(default_factory=dict)
    gps_lag: dict = field(default_factory=dict)
    dsm_valid_share: float = math.nan
    dsm_interpolated_share: float = 0.0
    dsm_matchable_share: float = math.nan  # of the stereo area: seen by both photos of a pair that can be matched
    dense_points: int = 0
    dense_pairs: int = 0
    stage_seconds: dict[str, float] = field(default_factory=dict)
    resumed_stages: list[str] = field(default_factory=list)
    total_seconds: float = 0.0
    peak_memory_mib: float = 0.0
    outputs: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    error: str | None = None

    def to_dict(self) -> dict:
        """The report as JSON values (non-finite numbers as null)."""
        return json_safe(asdict(self))

    def save_json(self, path: str | os.PathLike) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=1) + "\n")

    def save_png(self, path: str | os.PathLike, preview_rgba: np.ndarray | None = None,
                 extent_m: tuple[float, float, float, float] | None = None,
                 cameras_utm_m: np.ndarray | None = None, gps_utm_m: np.ndarray | None = None) -> None:
        """Orthophoto with model camera centres (blue) and GPS tags (red), and stage times.
        ``extent_m``: (west, east, south, north) of the preview in UTM metres."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, (ax_map, ax_time) = plt.subplots(1, 2, figsize=(13, 6), gridspec_kw={"width_ratios": [2, 1]})
        if preview_rgba is not None and extent_m is not None:
            ax_map.imshow(preview_rgba, extent=extent_m)
        if cameras_utm_m is not None and gps_utm_m is not None and len(cameras_utm_m):
            ax_map.scatter(gps_utm_m[:, 0], gps_utm_m[:, 1], s=14, c="red", label="GPS tag")
            ax_map.scatter(cameras_utm_m[:, 0], cameras_utm_m[:, 1], s=8, c="blue", label="reconstructed camera")
            for a, b in zip(cameras_utm_m, gps_utm_m, strict=True):
                ax_map.plot([a[0], b[0]], [a[1], b[1]], "k-", lw=0.8)
            ax_map.legend(loc="upper right", fontsize=8)
        ax_map.set_title(f"{len(self.registered)}/{len(self.photos_used)} photos registered, "
                         f"georef RMS {self.georef_rms_m:.2f} m, EPSG:{self.crs_epsg}", fontsize=10)
        ax_map.set_xlabel("easting (m)")
        ax_map.set_ylabel("northing (m)")
        ax_map.ticklabel_format(useOffset=False, style="plain")
        names = list(self.stage_seconds)
        ax_time.barh(names, [self.stage_seconds[n] for n in names],
                     color=["grey" if n in self.resumed_stages else "tab:blue" for n in names])
        ax_time.invert_yaxis()
        ax_time.set_xlabel("seconds (grey: resumed from an earlier run)")
        ax_time.set_title(f"total {self.total_seconds:.0f} s, peak memory {self.peak_memory_mib:.0f} MiB",
                          fontsize=10)
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
