"""Scores of a recovery run from the recorder's rows (no flight: rows written by hand)."""

from __future__ import annotations

import math

from skyfix.crps.recovery_report import Recorder


def _row(t_s: float, err_en_m: tuple[float, float] | None, alt_rel_m: float, mode: str) -> dict:
    """A row of d2 at the origin, ``alt_rel_m`` above home, with a fused fix off by ``err_en_m`` (E, N)."""
    row = {"t_s": t_s, "d2_east_m": 0.0, "d2_north_m": 0.0, "d2_up_m": alt_rel_m, "d2_alt_rel_m": alt_rel_m,
           "mode": mode, "sources": ""}
    if err_en_m is not None:
        row.update({"fused_east_m": err_en_m[0], "fused_north_m": err_en_m[1], "fused_up_m": alt_rel_m,
                    "fused_sigma_h_m": 1.0, "fused_cov_enu_m2": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]})
    return row


def test_fix_error_after_loss_is_the_largest_airborne_one_whatever_the_mode():
    rec = Recorder(None, ("d1", "d2", "d3"), 1, truth=lambda k: {})
    rec.t_loss = 10.0
    rec.rows = [_row(5.0, (9.0, 0.0), 15.0, "normal"),        # before the loss: not counted
                _row(10.0, (3.0, 4.0), 15.0, "normal"),       # a healthy baseline flies on in "normal": 5 m
                _row(11.0, None, 15.0, "hold"),               # no fix: nothing to score
                _row(12.0, (1.0, 1.0), 15.0, "return_home"),
                _row(13.0, (0.0, 7.0), 0.5, "return_home")]   # on the ground (<= 1 m above home): not counted
    assert math.isclose(rec.max_fix_error_after_loss_m(), 5.0)
    # the goal's figure counts only the recovering rows (a mode other than normal)
    assert math.isclose(rec.max_recovery_error_m(), math.sqrt(2.0))
    rec.rows = rec.rows[:1]
    assert math.isnan(rec.max_fix_error_after_loss_m())
