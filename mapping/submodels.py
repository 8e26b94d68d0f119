"""Split a survey's photos into submodels by GPS: balanced parts with an overlap band.

Each photo belongs to exactly one part's *core*; a submodel is its core plus every photo of another
part within ``overlap_m`` (horizontal GPS distance) of one of its core photos, so neighbouring
submodels share the photos along their boundary and can be aligned through them
(:mod:`skyfix.mapping.align`). Parts come from recursive bisection along the longer principal axis
of the GPS positions, cut in proportion to the parts each side gets, so core sizes differ by at most
one photo and every part is one contiguous piece of the survey. The result depends only on the
photos' names and positions (sorted by name first), never on the order they were listed in.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from skyfix.errors import InputError

__all__ = ["Submodel", "split_photos", "part_count", "save_split", "load_split"]


@dataclass(frozen=True)
class Submodel:
    """One submodel: ``core`` photos are its own (it owns the ground nearest them in the merge);
    ``shared`` photos belong to neighbours' cores and are reconstructed here too. Names sorted."""

    index: int
    core: tuple[str, ...]
    shared: tuple[str, ...] = field(default_factory=tuple)

    @property
    def photos(self) -> tuple[str, ...]:
        return tuple(sorted(self.core + self.shared))

    @property
    def name(self) -> str:
        return f"{self.index:03d}"

    def to_dict(self) -> dict:
        return {"index": self.index, "core": list(self.core), "shared": list(self.shared)}


def part_count(n_photos: int, target_photos: int) -> int:
    """How many parts ``n_photos`` make at about ``target_photos`` each (at least one)."""
    if target_photos < 3:
        raise InputError(f"--split: a submodel needs at least 3 photos to reconstruct, got {target_photos}")
    return max(1, round(n_photos / target_photos))


def split_photos(names: list[str], east_north_m: np.ndarray, target_photos: int,
                 overlap_m: float) -> list[Submodel]:
    """Partition photos (``names`` with horizontal GPS positions ``east_north_m`` (N, 2), local metres)
    into about ``len(names) / target_photos`` balanced parts, each extended by the photos of other
    parts within ``overlap_m`` of its core."""
    xy = np.asarray(east_north_m, dtype=float)
    if xy.ndim != 2 or xy.shape != (len(names), 2) or not np.isfinite(xy).all():
        raise InputError(f"split_photos: east_north_m must be ({len(names)}, 2) finite metres, got {xy.shape}")
    if len(set(names)) != len(names):
        raise InputError("split_photos: photo names must be unique")
    if not (math.isfinite(overlap_m) and overlap_m >= 0):
        raise InputError(f"--split-overlap must be >= 0 m, got {overlap_m}")
    order = np.argsort(np.asarray(names, dtype=object).astype(str), kind="stable")
    names = [names[i] for i in order]
    xy = xy[order]
    k = part_count(len(names), target_photos)
    parts = _bisect(np.arange(len(names)), xy, k)
    label = np.empty(len(names), dtype=int)
    for i, idx in enumerate(parts):
        label[idx] = i
    out = []
    for i, idx in enumerate(parts):
        others = np.flatnonzero(label != i)
        if len(others) and overlap_m > 0:
            d2 = ((xy[others, None, :] - xy[None, idx, :]) ** 2).sum(axis=2)  # (others, core)
            near = others[d2.min(axis=1) <= overlap_m ** 2]
        else:
            near = np.array([], dtype=int)
        out.append(Submodel(i, tuple(sorted(names[j] for j in idx)), tuple(sorted(names[j] for j in near))))
    return out


def _bisect(idx: np.ndarray, xy: np.ndarray, k: int) -> list[np.ndarray]:
    """``k`` contiguous parts of ``idx`` (sizes within one photo): cut along the principal axis."""
    if k <= 1 or len(idx) <= 1:
        return [idx]
    pts = xy[idx] - xy[idx].mean(axis=0)
    _, _, vt = np.linalg.svd(pts, full_matrices=False)
    axis = vt[0] if vt[0][np.argmax(np.abs(vt[0]))] > 0 else -vt[0]  # sign fixed: the same cut every run
    proj = pts @ axis
    order = idx[np.lexsort((idx, proj))]  # ties broken by the (name-sorted) index
    k_left = k // 2
    cut = round(len(idx) * k_left / k)
    return _bisect(order[:cut], xy, k_left) + _bisect(order[cut:], xy, k - k_left)


def save_split(path: str | os.PathLike, submodels: list[Submodel], target_photos: int, overlap_m: float) -> None:
    """``split.json``: the options and the parts (what a resumed run must find unchanged)."""
    Path(path).write_text(json.dumps({"target_photos": target_photos, "overlap_m": overlap_m,
                                      "submodels": [s.to_dict() for s in submodels]}, indent=1) + "\n")


def load_split(path: str | os.PathLike) -> tuple[list[Submodel], int, float] | None:
    """The split saved by :func:`save_split`, or None when there is none."""
    p = Path(path)
    if not p.exists():
        return None
    data = json.loads(p.read_text())
    subs = [Submodel(int(s["index"]), tuple(s["core"]), tuple(s["shared"])) for s in data["submodels"]]
    return subs, int(data["target_photos"]), float(data["overlap_m"])
