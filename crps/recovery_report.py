"""Scoring and files of a recovery run: the truth recorder, trajectory.csv / .png and report.json.

The recorder reads the simulator's truth next to what the lost drone's service believes (its
fused estimate, its recovery mode) and what each helper's camera delivered; only the scores use
the truth. Positions are world ENU metres of the simulator; times simulated seconds.
"""

from __future__ import annotations

import csv
import json
import math
import threading
from pathlib import Path

import numpy as np

HOME_RADIUS_M = 3.0


class Recorder:
    """Truth and belief samples of a run with drones ``ids`` (index ``lost`` is the one that loses GNSS)."""

    def __init__(self, sim, ids: tuple[str, ...], lost: int, truth=None, common=None) -> None:
        """``truth(k)`` the truth of drone ``k`` (default: the simulator's vehicle ``k``); ``common`` the GNSS
        error every receiver of the run shares (a :class:`skyfix.datasets.gnss_error.CommonGnssError`, or None)."""
        self.sim, self.ids, self.lost, self.common = sim, ids, lost, common
        self.truth = truth or sim.truth
        self.rows: list[dict] = []
        # (helper index, t_s, target, detected, in view, searched: False when the eye did not look, e.g. the
        # target below the helper's horizon)
        self.frames: list[tuple[int, float, str, bool, bool, bool]] = []
        self.home_enu: np.ndarray | None = None
        self.t_loss: float | None = None
        self._lock = threading.Lock()

    def homes_now(self) -> None:
        """The true take-off points (what "home" means for the landing error)."""
        self.home_enu = np.array([[self.truth(i)[k] for k in ("east_m", "north_m", "up_m")]
                                  for i in range(len(self.ids))])

    def frame_scorer(self, index: int, camera, key_of):
        """``on_frame`` for helper ``index``'s eye: whether the target was in view (the camera's truth, where
        ``key_of(drone_id)`` names the target)."""
        def score(frame, target_id: str, detected: bool | None) -> None:
            truth = getattr(camera, "last_truth", None)
            in_view = truth is not None and target_id in self.ids and truth.in_view(key_of(target_id))
            with self._lock:
                self.frames.append((index, float(frame.t_s), target_id, bool(detected), bool(in_view),
                                    detected is not None))
        return score

    def sample(self, services) -> None:
        """One row: every drone's truth, the lost drone's fused fix and mode (and its simulated autopilot's
        estimate and home, ``ap_*``: where the autopilot believes it is and lands; absent for SITL)."""
        t = self.sim.time_s
        truth = [self.truth(i) for i in range(len(self.ids))]
        row = {"t_s": round(t, 3)}
        for drone_id, tr in zip(self.ids, truth, strict=True):
            row.update({f"{drone_id}_east_m": tr["east_m"], f"{drone_id}_north_m": tr["north_m"],
                        f"{drone_id}_up_m": tr["up_m"], f"{drone_id}_alt_rel_m": tr["alt_rel_m"]})
        lost = truth[self.lost]
        if "est_east_m" in lost:  # the simulated autopilot's own estimate and home (scoring: where it lands)
            row.update({f"ap_{k}": lost[k] for k in ("est_east_m", "est_north_m", "home_east_m", "home_north_m")})
        svc = services[self.lost]
        fix = svc.node.fix(svc.cfg.drone_id, t) if svc.node is not None else None
        est = svc.node.latest.get(svc.cfg.drone_id) if svc.node is not None else None
        if fix is not None:
            e, n, u = (float(c) for c in self.sim.world.to_enu(fix.lat_deg, fix.lon_deg, fix.alt_m))
            row.update({"fused_east_m": e, "fused_north_m": n, "fused_up_m": u,
                        "fused_sigma_h_m": fix.sigma_horizontal_m, "fused_cov_enu_m2": fix.cov_enu_m2,
                        "fused_cov_frame_enu_m2": svc.node.fix(svc.cfg.drone_id, t, frame=True).cov_enu_m2})
        if self.common is not None and t >= 0.0:
            c = self.common.at(t)
            row.update({"common_east_m": float(c[0]), "common_north_m": float(c[1]), "common_up_m": float(c[2])})
        row["sources"] = " ".join(est.sources) if est is not None else ""
        row["mode"] = svc.help.mode.value if svc.help is not None else ""
        with self._lock:
            self.rows.append(row)

    # -- scores ------------------------------------------------------------------------------
    def _after_loss(self) -> list[dict]:
        return [r for r in self.rows if self.t_loss is not None and r["t_s"] >= self.t_loss]

    def landing_error_m(self) -> float:
        if not self.rows or self.home_enu is None:
            return math.nan
        last, d = self.rows[-1], self.ids[self.lost]
        return float(math.hypot(last[f"{d}_east_m"] - self.home_enu[self.lost, 0],
                                last[f"{d}_north_m"] - self.home_enu[self.lost, 1]))

    def return_speed_max_mps(self, window_s: float = 2.0) -> float:
        """The lost drone's largest true horizontal speed while it flies home (mode return_home), m/s: its
        displacement over ``window_s`` (an external autopilot's truth arrives on its own clock, so consecutive
        samples' spacing is not its motion's). NaN: no such window."""
        d = self.ids[self.lost]
        rows = [r for r in self._after_loss() if r["mode"] == "return_home"]
        t = np.array([r["t_s"] for r in rows])
        xy = np.array([[r[f"{d}_east_m"], r[f"{d}_north_m"]] for r in rows]).reshape(-1, 2)
        ends = np.searchsorted(t, t + window_s)
        ok = ends < len(t)
        if not ok.any():
            return math.nan
        starts = np.flatnonzero(ok)
        return float(np.max(np.linalg.norm(xy[ends[ok]] - xy[starts], axis=1) / (t[ends[ok]] - t[starts])))

    def first_fused_fix_s(self) -> float:
        """Loss to the first estimate of the lost drone resting on a helper's observation, s (NaN: none)."""
        for r in self._after_loss():
            if "relative:" in r["sources"]:
                return r["t_s"] - self.t_loss
        return math.nan

    def _recovering(self) -> list[dict]:
        d = self.ids[self.lost]
        return [r for r in self._after_loss() if r["mode"] not in ("", "normal") and "fused_east_m" in r
                and r[f"{d}_alt_rel_m"] > 1.0]

    def _errors(self, frame: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) fused - true ENU errors while recovering, (N, 3, 3) their covariances (``frame``: in the swarm's
        GNSS frame, errors less the shared GNSS error, covariances the fusion's in that frame)."""
        d, rows = self.ids[self.lost], self._recovering()
        if not rows:
            return np.zeros((0, 3)), np.zeros((0, 3, 3))
        err = np.array([[r["fused_east_m"] - r[f"{d}_east_m"], r["fused_north_m"] - r[f"{d}_north_m"],
                         r["fused_up_m"] - r[f"{d}_up_m"]] for r in rows])
        if frame:
            return err - self.common_errors(), np.array([r["fused_cov_frame_enu_m2"] for r in rows])
        return err, np.array([r["fused_cov_enu_m2"] for r in rows])

    def max_recovery_error_m(self) -> float:
        err, _ = self._errors()
        return float(np.hypot(err[:, 0], err[:, 1]).max()) if len(err) else math.nan

    def common_errors(self) -> np.ndarray:
        """(N, 3) the GNSS error all receivers shared at each sample while recovering (zeros: none shared).
        The helpers' fixes carry it, so a fix resting on their observations carries it too: no receiver of
        the swarm can see it (the error against the swarm's GNSS frame is the fused one minus this)."""
        return np.array([[r.get(f"common_{k}_m", 0.0) for k in ("east", "north", "up")] for r in self._recovering()]
                        ).reshape(-1, 3)

    def max_fix_error_after_loss_m(self) -> float:
        """The largest horizontal error of the lost drone's fused fix from the loss on while airborne (> 1 m above
        home), whatever it rests on: in a healthy-GNSS baseline, what its own receiver allowed over its return."""
        d = self.ids[self.lost]
        err = [math.hypot(r["fused_east_m"] - r[f"{d}_east_m"], r["fused_north_m"] - r[f"{d}_north_m"])
               for r in self._after_loss() if "fused_east_m" in r and r[f"{d}_alt_rel_m"] > 1.0]
        return max(err) if err else math.nan

    def max_recovery_error_gnss_frame_m(self) -> float:
        """The largest horizontal error while recovering against the swarm's GNSS frame (truth + common error)."""
        err, _ = self._errors()
        rel = err - self.common_errors()
        return float(np.hypot(rel[:, 0], rel[:, 1]).max()) if len(rel) else math.nan

    def error_around(self, t0_s: float, t1_s: float) -> dict[str, float]:
        """While recovering: the largest horizontal error outside [t0_s, t1_s] (m) and, inside it, the largest
        error in units of the stated horizontal sigma (honesty while a window of inputs was missing)."""
        rows, (err, _) = self._recovering(), self._errors()
        if not rows:
            return {"max_error_outside_h_m": math.nan, "max_error_inside_over_sigma": math.nan}
        t = np.array([r["t_s"] for r in rows])
        err_h = np.hypot(err[:, 0], err[:, 1])
        sigma_h = np.array([r["fused_sigma_h_m"] for r in rows])
        inside = (t >= t0_s) & (t <= t1_s)
        return {"max_error_outside_h_m": float(err_h[~inside].max()) if (~inside).any() else math.nan,
                "max_error_inside_over_sigma": float((err_h[inside] / sigma_h[inside]).max()) if inside.any()
                else math.nan}

    def min_separation_m(self) -> float:
        if not self.rows:
            return math.nan
        pos = np.array([[[r[f"{d}_east_m"], r[f"{d}_north_m"], r[f"{d}_up_m"]] for d in self.ids] for r in self.rows])
        n = len(self.ids)
        gaps = [np.linalg.norm(pos[:, i] - pos[:, j], axis=1).min() for i in range(n) for j in range(i + 1, n)]
        return float(min(gaps))

    def gnss_trusted_again_s(self, back_s: float) -> float:
        """First time after ``back_s`` that the lost drone's estimate uses GNSS again (NaN: never)."""
        if not math.isfinite(back_s):
            return math.nan
        return next((r["t_s"] for r in self.rows if r["t_s"] >= back_s and "gnss" in r["sources"].split()), math.nan)

    def detection_share(self) -> float:
        """Share of the frames searched with the target in view in which it was detected (NaN: none)."""
        with self._lock:
            in_view = [f for f in self.frames if f[4] and f[5]]
        return float(np.mean([f[3] for f in in_view])) if in_view else math.nan

    def figures(self) -> dict[str, float]:
        err, cov = self._errors()
        nees = [float(e @ np.linalg.solve(c, e)) for e, c in zip(err, cov, strict=True)]
        nees_frame = [float(e @ np.linalg.solve(c, e)) for e, c in zip(*self._errors(frame=True), strict=True)]
        with self._lock:
            frames = list(self.frames)
        final = self._final()
        common_h = np.hypot(*self.common_errors()[:, :2].T)
        return {**final, "max_recovery_error_gnss_frame_h_m": self.max_recovery_error_gnss_frame_m(),
                "common_gnss_error_max_h_m": float(common_h.max()) if len(common_h) else math.nan,
                "fix_error_after_loss_max_h_m": self.max_fix_error_after_loss_m(),
                "return_speed_max_mps": self.return_speed_max_mps(),
                "recovery_error_rms_h_m": float(np.sqrt(np.mean(err[:, 0] ** 2 + err[:, 1] ** 2)))
                if len(err) else math.nan,
                "recovery_mean_nees_3dof": float(np.mean(nees)) if nees else math.nan,
                "recovery_mean_nees_frame_3dof": float(np.mean(nees_frame)) if nees_frame else math.nan,
                "helper_frames": float(len(frames)), "helper_frames_in_view": float(sum(f[4] for f in frames)),
                "helper_frames_searched_in_view": float(sum(f[4] and f[5] for f in frames)),
                "helper_frames_detected": float(sum(f[3] for f in frames))}


    def _final(self) -> dict[str, float]:
        """The lost drone's true final position (world ENU, above home) and its fused error there."""
        d = self.ids[self.lost]
        if not self.rows:
            return {}
        last = self.rows[-1]
        out = {f"final_{k}": float(last[f"{d}_{k}"]) for k in ("east_m", "north_m", "up_m", "alt_rel_m")}
        fused = next((r for r in reversed(self.rows) if "fused_east_m" in r), None)
        out["final_fused_error_h_m"] = math.nan if fused is None else float(
            math.hypot(fused["fused_east_m"] - fused[f"{d}_east_m"], fused["fused_north_m"] - fused[f"{d}_north_m"]))
        return out


def _write_csv(path: Path, rows: list[dict]) -> None:
    matrices = ("fused_cov_enu_m2", "fused_cov_frame_enu_m2")  # report.json has the figures drawn from them
    keys = [k for k in (rows[0] if rows else {"t_s": 0}) if k not in matrices]
    for r in rows:  # rows before the first fix lack the fused columns
        keys += [k for k in r if k not in keys and k not in matrices]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        writer.writeheader()
        for r in rows:
            writer.writerow({k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()})


def _plot(path: Path, rec: Recorder, result) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 8))
    colours = ["tab:blue", "tab:orange", "tab:green"]
    for k, d in enumerate(rec.ids):
        e = np.array([r[f"{d}_east_m"] for r in rec.rows])
        n = np.array([r[f"{d}_north_m"] for r in rec.rows])
        label = f"{d} (truth)" + (", loses GNSS" if k == rec.lost else ", helper")
        ax.plot(e, n, "-", color=colours[k % 3], lw=1.5, label=label)
        if rec.home_enu is not None:
            ax.plot(*rec.home_enu[k, :2], "^", color=colours[k % 3], ms=9)
    rows = rec._recovering()
    if rows:
        ax.plot([r["fused_east_m"] for r in rows], [r["fused_north_m"] for r in rows], ".", color="red", ms=2,
                label=f"{rec.ids[rec.lost]} fused position flown on (GPS_INPUT)")
    d = rec.ids[rec.lost]
    loss = next((r for r in rec.rows if rec.t_loss is not None and r["t_s"] >= rec.t_loss), None)
    if loss is not None:
        ax.plot(loss[f"{d}_east_m"], loss[f"{d}_north_m"], "X", color="red", ms=11, label="GNSS lost")
    if rec.rows and rec.home_enu is not None:
        home = rec.home_enu[rec.lost, :2]
        ax.add_patch(plt.Circle(home, HOME_RADIUS_M, fill=False, ls="--", color="k", label="3 m around home"))
        ax.plot(rec.rows[-1][f"{d}_east_m"], rec.rows[-1][f"{d}_north_m"], "o", mfc="none", color="red", ms=10,
                label=f"{d} landed ({result.landing_error_m:.2f} m from home)")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_title(f"skyfix demo: {d} loses GNSS, helpers' cameras bring it home ({result.outcome})\n(^ take-off points)")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_outputs(out: Path, rec: Recorder, result, logs: list[str]) -> dict[str, str]:
    """trajectory.csv, trajectory.png and report.json in ``out``; the names of every file written."""
    files = {"trajectory_csv": str(out / "trajectory.csv"), "trajectory_png": str(out / "trajectory.png"),
             "report_json": str(out / "report.json")}
    files.update({f"log_{Path(name).stem}": str(out / name) for name in logs if (out / name).exists()})
    result.files = files
    _write_csv(out / "trajectory.csv", rec.rows)
    _plot(out / "trajectory.png", rec, result)
    (out / "report.json").write_text(json.dumps(_plain(result.to_dict()), indent=2))
    return files


def _plain(value):
    """JSON-safe: NaN/inf -> null, numpy scalars -> Python."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
