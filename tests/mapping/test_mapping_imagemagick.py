"""Same geometry as ImageMagick's -distort barrel (runs where Debian's imagemagick is installed)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from skyfix.mapping.correct import Undistortion
from skyfix.mapping.lens import parse_barrel

DATA = Path(__file__).parent / "data"


def _imagemagick() -> str | None:
    for cmd in ("/usr/bin/convert-im6.q16", "/usr/bin/convert", "/usr/bin/magick"):
        try:
            out = subprocess.run([cmd, "-version"], capture_output=True, text=True, timeout=10)
        except (OSError, subprocess.TimeoutExpired):
            continue
        if out.stdout.startswith("Version: ImageMagick"):
            return cmd
    return None


CONVERT = _imagemagick()


@pytest.mark.skipif(CONVERT is None, reason="ImageMagick is not installed (apt-get install imagemagick)")
@pytest.mark.parametrize("coeffs,size", [("0.1 -0.32 0", (400, 300)), ("0.02 -0.1 0.05 1.1", (300, 420))])
def test_barrel_geometry_matches_imagemagick(tmp_path, coeffs, size):
    raw = cv2.resize(cv2.imread(str(DATA / "IMG_0459.jpg")), size, interpolation=cv2.INTER_AREA)
    src, dst = tmp_path / "raw.png", tmp_path / "im.png"
    cv2.imwrite(str(src), raw)
    # -filter point: ImageMagick samples with its bilinear interpolation instead of EWA.
    subprocess.run([CONVERT, str(src), "-filter", "point", "-distort", "barrel", coeffs, str(dst)], check=True)
    theirs = cv2.imread(str(dst)).astype(float)
    ours = Undistortion.for_barrel(parse_barrel(coeffs), *size).apply(raw).astype(float)
    # Equal geometry leaves rounding-level differences (1/32 px tables, 8-bit rounding).
    assert np.mean(np.abs(ours - theirs)) < 1.0
    # A geometry error of half a pixel would show clearly: shift ours and compare.
    shifted = Undistortion.for_barrel(parse_barrel(coeffs), *size)
    moved = cv2.remap(raw, shifted.map_x + 0.5, shifted.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    assert np.mean(np.abs(moved.astype(float) - theirs)) > 2 * np.mean(np.abs(ours - theirs))
