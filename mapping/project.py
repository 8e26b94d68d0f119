"""A photo-to-model project folder (:mod:`skyfix.mapping.pipeline`): its paths, the stage
markers, and the options each stage's result depends on (a marker records them; a run with
different ones re-runs the stage).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

__all__ = ["STAGES", "Project", "stage_options"]

STAGES = ("photos", "correct", "features", "matches", "mapping", "georef", "dsm", "ortho", "export")

#: The options each stage's result depends on (its own and, for the stages that are
#: never redone by a change upstream, those of the stages it reads). A stage whose
#: recorded options differ runs again, and every later stage with it.
_STAGE_OPTIONS = {
    "photos": (), "correct": ("barrel",),
    "features": ("barrel", "calibration", "max_image_size_px", "max_features"),
    "matches": ("barrel", "calibration", "max_image_size_px", "max_features", "exhaustive_max_photos",
                "spatial_neighbours", "seed"),
    "mapping": ("calibration", "refine_focal", "gps_sigma_m", "seed"),
    "georef": ("georef_max_error_m", "two_view_max_offset_m", "two_view_max_vertical_m", "estimate_gps_lag"),
    "dsm": ("dense", "dense_scale", "dense_cell_px", "dsm_resolution_m", "max_dense_points", "dsm_fill_max_m2",
            "seed"),
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


class Project:
    """Paths of a project folder and the stage markers."""

    def __init__(self, out_dir: Path) -> None:
        self.root = out_dir
        self.work = out_dir / "work"
        self.stages = self.work / "stages"
        self.database = self.work / "database.db"
        self.sparse = self.work / "sparse"
        self.georef = self.work / "georef"
        self.corrected = self.work / "corrected"
        self.stages.mkdir(parents=True, exist_ok=True)

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
