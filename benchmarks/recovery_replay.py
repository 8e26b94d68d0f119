"""Would other fusion settings have landed the lost drone closer? Its recorded inputs, fused again.

``benchmarks/recovery.py -o DIR`` keeps, per seed, the lost drone's fusion log (``d2.mcap``: every
GNSS fix, velocity, peer fix and helper observation its engine took) and the simulator's truth
(``trajectory.csv``). This replays each log through a fresh engine (:func:`skyfix.fusion.replay`),
once as recorded and once per variant (``--variant NAME:KEY=VALUE[,KEY=VALUE]``, KEY a
:class:`~skyfix.fusion.FusionConfig` field, or ``rel_cov_scale`` / ``vel_sigma_scale``, which scale
the helpers' observation covariances / the lost drone's velocity sigma in the log), and prints
per seed and as medians: the fix's horizontal error at touchdown against the swarm's GNSS frame
(truth plus the error all receivers share), the landing error it predicts, and how honest the replayed
sigma is from the loss to touchdown (mean (error / sigma_h)^2 against the truth, sigma_h the larger
horizontal axis' 1-sigma: 1-2 honest, as ``recovery_diagnose.py`` scores the flown fix).

The prediction holds the flown trajectory fixed: the drone lands where its fix says home is, so a
fix at touchdown moved by d moves the landing by -d (the recorded runs land within ~0.1 m of their
own fix, ``recovery_diagnose.py --frames``). It ignores that a different fix would have steered
the flight differently before touchdown; a variant worth keeping is then flown by
``benchmarks/recovery.py``. Scoring only: truth is read here, never by the replayed engine.
The replay as recorded must reproduce the flown fix (printed: its largest deviation at touchdown).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import recovery_diagnose as rd  # noqa: E402  (a sibling script: the trajectory readers)

LOST = rd.LOST
LOG_SCALES = ("rel_cov_scale", "vel_sigma_scale")


def _variant(text: str) -> tuple[str, dict]:
    name, _, body = text.partition(":")
    if not body:
        raise SystemExit(f"--variant {text!r}: expected NAME:KEY=VALUE[,KEY=VALUE]")
    settings = {}
    for item in body.split(","):
        key, _, value = item.partition("=")
        settings[key.strip()] = json.loads(value)
    return name, settings


def _replay(log_path: Path, settings: dict) -> tuple[np.ndarray, np.ndarray]:
    """(time_s, east/north m in the log's frame) of the lost drone's replayed fix under ``settings``."""
    from skyfix.fusion.config import FusionConfig
    from skyfix.fusion.log_mcap import read_mcap_log
    from skyfix.fusion.replay import replay

    settings = dict(settings)
    scales = {k: settings.pop(k) for k in LOG_SCALES if k in settings}
    header, _ = read_mcap_log(log_path)

    def edit(r: dict) -> dict:
        if "vel_sigma_scale" in scales and r["op"] == "velocity" and r["args"]["drone_id"] == LOST:
            return dict(r, args=dict(r["args"], sigma_mps=r["args"]["sigma_mps"] * scales["vel_sigma_scale"]))
        if "rel_cov_scale" in scales and r["op"] == "relative":
            obs = r["args"]["obs"]
            return dict(r, args={"obs": dataclasses.replace(obs, cov_enu_m2=obs.cov_enu_m2 * scales["rel_cov_scale"])})
        return r

    config = dataclasses.replace(FusionConfig.from_dict(header["config"]), **settings)
    result = replay(log_path, show_progress=False, config=config, edit=edit if scales else None)
    t, enu, cov = result.fused[LOST].arrays()
    return t, enu[:, :2], np.sqrt(np.linalg.eigvalsh(cov[:, :2, :2])[:, -1])


def _honesty(t: np.ndarray, err_h: np.ndarray, ts: np.ndarray, sigma_h: np.ndarray, use: np.ndarray) -> float:
    """Mean (horizontal error / stated sigma_h)^2 over the rows ``use`` (sigma_h: the larger axis' 1-sigma, so
    1-2 is honest, as recovery_diagnose.py's), the replayed sigma taken at the rows' times."""
    sigma = np.interp(t[use], ts, sigma_h)
    return float(np.mean(np.sum(err_h[use] ** 2, axis=1) / sigma**2)) if use.any() else float("nan")


def score(run: Path, variants: list[tuple[str, dict]]) -> dict[str, tuple[float, float, float]]:
    """Per variant (and 'as recorded'): (fix error at touchdown vs the swarm's GNSS frame, predicted landing, m;
    mean (error / stated sigma)^2 against the truth from the loss while airborne)."""
    rows = rd._trajectory(run)
    t = rd._columns(rows, ("t_s",))[:, 0]
    truth = rd._columns(rows, (f"{LOST}_east_m", f"{LOST}_north_m"))
    common = np.nan_to_num(rd._columns(rows, ("common_east_m", "common_north_m")))
    flown = rd._columns(rows, ("fused_east_m", "fused_north_m"))
    airborne = np.flatnonzero(rd._columns(rows, (f"{LOST}_alt_rel_m",))[:, 0] > 0.3)
    td = int(airborne[-1])
    landed = truth[td] - truth[0]
    t_loss = rd._loss_time_s(run)
    recovering = np.zeros(len(t), bool) if t_loss is None else (t >= t_loss) & (np.arange(len(t)) <= td)
    out = {}
    offset = None
    for name, settings in [("as recorded", {})] + variants:
        ts, fix, sigma_h = _replay(run / f"{LOST}.mcap", settings)
        at_td = np.array([np.interp(t[td], ts, fix[:, i]) for i in range(2)])
        if offset is None:  # the log's frame is the lost drone's: its offset from the world's, from the flown fix
            ok = np.isfinite(flown[:, 0]) & (t >= ts[0]) & (t <= ts[-1])
            offset = np.median(flown[ok] - np.stack([np.interp(t[ok], ts, fix[:, i]) for i in range(2)], 1), axis=0)
            out["deviation"] = (float(np.linalg.norm(at_td + offset - flown[td])), float("nan"), float("nan"))
        moved = at_td + offset - flown[td]
        err_h = np.stack([np.interp(t, ts, fix[:, i]) for i in range(2)], 1) + offset - truth
        use = recovering & (t >= ts[0]) & (t <= ts[-1])
        out[name] = (float(np.linalg.norm(at_td + offset - truth[td] - common[td])),
                     float(np.linalg.norm(landed - moved)), _honesty(t, err_h, ts, sigma_h, use))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", type=Path, help="a benchmarks/recovery.py output folder (seed_<n>/recovery)")
    ap.add_argument("--variant", action="append", default=[], type=_variant, metavar="NAME:KEY=VALUE[,...]",
                    help="fusion settings to replay with (repeatable)")
    args = ap.parse_args(argv)
    runs = sorted((p for p in args.runs.glob("seed_*/recovery") if (p / f"{LOST}.mcap").exists()),
                  key=lambda p: int(p.parent.name.split("_")[1]))
    if not runs:
        print(f"no seed_<n>/recovery/{LOST}.mcap under {args.runs}", file=sys.stderr)
        return 2
    names = ["as recorded"] + [n for n, _ in args.variant]
    table = {n: [] for n in names}
    worst_dev = 0.0
    for run in runs:
        found = score(run, args.variant)
        worst_dev = max(worst_dev, found.pop("deviation")[0])
        print(f"{run.parent.name}: " + "; ".join(f"{n} {found[n][0]:.2f} m, landing {found[n][1]:.2f} m, "
                                                f"(err/sigma)^2 {found[n][2]:.2f}" for n in names), flush=True)
        for n in names:
            table[n].append(found[n])
    print(f"the replay as recorded against the flown fix at touchdown: up to {worst_dev:.2f} m apart")
    for n in names:
        v = np.array(table[n])
        print(f"{n:>24}: fix at touchdown vs the swarm's GNSS frame median {np.median(v[:, 0]):.2f} m; "
              f"predicted landing median {np.median(v[:, 1]):.2f} m, mean {v[:, 1].mean():.2f} m; stated sigma "
              f"from the loss, median of mean (error / sigma_h)^2 against the truth {np.nanmedian(v[:, 2]):.2f} "
              "(honest: 1-2)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
