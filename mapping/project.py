"""A photo-to-model project folder (:mod:`skyfix.mapping.pipeline`): the one object that
knows its file names (OpenSfM's DataSet pattern: stages ask it for paths, never build them),
the stage markers, the options each stage's result depends on (a marker records them; a
run with different ones re-runs the stage), and :class:`RunState`, what the stages hand on.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["STAGES", "Project", "RunState", "stage_options"]

STAGES = ("photos", "correct", "features", "matches", "mapping", "georef", "dsm", "ortho", "export")

#: The options each stage's result depends on (its own and, for the stages that are
#: never redone by a change upstream, those of the stages it reads). A stage whose
#: recorded options differ runs again, and every later stage with it.
_STAGE_OPTIONS = {
    "photos": (), "correct": ("barrel",),
    "features": ("barrel", "calibration", "max_image_size_px", "max_features"),
    "matches": ("barrel", "calibration", "max_image_size_px", "max_features", "exhaustive_max_photos",
                "spatial_neighbours", "seed", "match_threads"),
    "mapping": ("calibration", "shared_lens", "refine_focal", "gps_sigma_m", "seed", "sfm_threads"),
    "georef": ("georef_max_error_m", "two_view_max_offset_m", "two_view_max_vertical_m", "estimate_gps_lag"),
    "dsm": ("dense", "dense_scale", "dense_fill_scales", "dense_local_norm_px", "dense_cell_px", "dsm_resolution_m",
            "max_dense_points", "dsm_fill_max_m2", "seed"),
    "ortho": ("resolution_cm", "max_ortho_mpx", "ortho_seams", "seam_band_px", "blend_power"),
    "export": (),
}


def stage_options(config, stage: str) -> dict:
    """The options ``stage`` depends on, as JSON values (objects by their repr)."""
    def plain(value):
        if value is None or isinstance(value, (bool, int, float, str)):
            return value
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        return repr(value)

    return {name: plain(getattr(config, name)) for name in _STAGE_OPTIONS[stage]}


@dataclass
class RunState:
    """What one pipeline run's stages hand to the later ones (in memory; markers and the
    project's files are what survives a run)."""

    photos: list = field(default_factory=list)  # mapping.photos.Photo, as used (corrected ones after `correct`)
    image_dir: Path | None = None                # where the photos used are (the input or the corrected folder)
    models: list = field(default_factory=list)   # pycolmap.Reconstruction of `mapping`, then of `georef`
    pairs: list = field(default_factory=list)    # (pycolmap.Reconstruction, sfm.PairModel) two-view models
    velocities: dict = field(default_factory=dict)  # photo name -> GPS velocity ENU m/s (gps lag)
    frame: Any = None                            # skyfix.geo.LocalFrame of the georeference (None: no GPS)
    referenced: list = field(default_factory=list)    # georeferenced models
    unreferenced: list = field(default_factory=list)  # models left in their arbitrary frame
    dsm: Any = None                              # mapping.dsm.Dsm (None: skipped)
    ortho_grid: dict | None = None               # the orthophoto's Grid as a dict (None: skipped)


class Project:
    """A project folder: every file's path, and the stage markers."""

    def __init__(self, out_dir: Path) -> None:
        self.root = out_dir
        self.work = out_dir / "work"
        self.stages = self.work / "stages"
        self.database = self.work / "database.db"
        self.sparse = self.work / "sparse"
        self.pairs = self.sparse / "pairs"
        self.georef = self.work / "georef"
        self.corrected = self.work / "corrected"
        self.dense_points = self.work / "dense_points.npz"
        self.dsm_surface = self.work / "dsm_surface.npy"
        self.dsm_filled = self.work / "dsm_filled.npy"
        # the deliverables, in the project's root
        self.report_json = out_dir / "report.json"
        self.report_png = out_dir / "report.png"
        self.points_ply = out_dir / "points.ply"
        self.cameras_geojson = out_dir / "cameras.geojson"
        self.dsm_tif = out_dir / "dsm.tif"
        self.dsm_interpolated_tif = out_dir / "dsm_interpolated.tif"
        self.orthophoto_tif = out_dir / "orthophoto.tif"
        self.orthophoto_png = out_dir / "orthophoto.png"
        self.stages.mkdir(parents=True, exist_ok=True)

    def georef_model(self, index: int) -> Path:
        """Folder of georeferenced model ``index`` (created)."""
        path = self.georef / str(index)
        path.mkdir(parents=True, exist_ok=True)
        return path

    def marker(self, stage: str) -> dict | None:
        path = self.stages / f"{stage}.json"
        return json.loads(path.read_text()) if path.exists() else None

    def mark(self, stage: str, data: dict) -> None:
        tmp = self.stages / f"{stage}.json.part"
        tmp.write_text(json.dumps(data, indent=1))
        os.replace(tmp, self.stages / f"{stage}.json")

    def reset_database(self, stage: str) -> None:
        """Before re-running ``features`` (the database goes) or ``matches`` (its matches go):
        pycolmap skips images and pairs the database already holds."""
        if stage == "features":
            for suffix in ("", "-wal", "-shm"):
                Path(f"{self.database}{suffix}").unlink(missing_ok=True)
        elif self.database.exists():
            import pycolmap

            db = pycolmap.Database.open(str(self.database))
            try:
                db.clear_matches()
                db.clear_two_view_geometries()
            finally:
                db.close()

    def clear_from(self, stage: str) -> None:
        for later in STAGES[STAGES.index(stage):]:
            (self.stages / f"{later}.json").unlink(missing_ok=True)
