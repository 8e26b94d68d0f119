"""Helpers the mapping commands share: argument types, and errors that name the user's flags."""

from __future__ import annotations

import argparse

__all__ = ["FLAG_NAMES", "flags_named", "parse_drone", "parse_latlon", "parse_size"]


#: Library parameter names -> the flags a user typed, so errors name what the user can change.
FLAG_NAMES = {"step_m": "--step", "altitude_m": "--alt", "hold_s": "--hold", "forward_overlap": "--forward",
              "side_overlap": "--side", "heading_deg": "--heading", "turnaround_m": "--turnaround",
              "joining_drones": "--joining", "growth_per_drone": "--growth", "alarm_latlon": "--alarm",
              "next_index": "--next-index", "stopped_at_latlon": "--stopped-at", "speed_mps": "--speed",
              "jpeg_quality": "--quality", "workers": "--workers", "resolution_cm": "--resolution-cm",
              "dsm_resolution_m": "--dsm-resolution-m", "dense_scale": "--dense-scale",
              "max_ortho_mpx": "--max-ortho-mpx", "max_image_size_px": "--max-image-size",
              "max_features": "--max-features", "sfm_threads": "--sfm-threads", "match_threads": "--match-threads", "threads": "--threads"}


def flags_named(func):
    """Wrap a command function: a skyfix error whose message names library parameters
    (``step_m``) is raised again, same type, naming the command's flags (``--step``)."""
    import functools
    import re

    from skyfix.errors import SkyfixError

    pattern = re.compile(r"(?<![-\w])(" + "|".join(FLAG_NAMES) + r")\b")  # not inside a flag already named

    @functools.wraps(func)
    def run(args: argparse.Namespace) -> int:
        try:
            return func(args)
        except SkyfixError as exc:
            text = pattern.sub(lambda m: FLAG_NAMES[m.group(1)], str(exc))
            if text == str(exc):
                raise
            try:
                renamed = type(exc)(text)
            except TypeError:
                raise exc from None
            raise renamed from exc

    return run


def parse_latlon(text: str) -> tuple[float, float]:
    """'lat,lon' -> (lat_deg, lon_deg)."""
    try:
        lat, lon = (float(p) for p in text.replace(" ", "").split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'lat,lon' in degrees, got {text!r}") from None
    return lat, lon


def parse_drone(text: str) -> tuple[str, tuple[float, float]]:
    """'ID=lat,lon' -> (id, (lat, lon))."""
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected 'ID=lat,lon', got {text!r}")
    name, pos = text.split("=", 1)
    return name.strip(), parse_latlon(pos)


def parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(p) for p in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels, got {text!r}") from None
    return w, h
