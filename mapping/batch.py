"""Correct a folder of photos: remap tables built once per image size, photos in parallel.

Threads share the tables and hold at most two photos each, so memory stays bounded
whatever the number of photos. A photo that cannot be corrected (corrupt JPEG, missing EXIF, size
that does not fit a calibration) is logged, reported and skipped; the batch goes on.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, as_completed, wait
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import simplejpeg

from skyfix import validate
from skyfix.camera import Camera
from skyfix.distortion import Barrel
from skyfix.errors import DataError, InputError, SkyfixError
from skyfix.mapping.correct import Undistortion
from skyfix.mapping.exif import PhotoMetadata, jpeg_quality, read_metadata, transfer_metadata

__all__ = ["BatchReport", "CorrectionSpec", "PhotoResult", "correct_photos", "list_photos"]

log = logging.getLogger(__name__)

PHOTO_SUFFIXES = (".jpg", ".jpeg")
_SUBSAMPLING = ("444", "422", "420", "440", "411")


@dataclass(frozen=True)
class CorrectionSpec:
    """How to correct photos: exactly one of ``barrel`` or ``camera`` (a calibrated camera).

    ``crop``: keep only pixels that sample inside the raw image. ``jpeg_quality``: 1-100, or
    None to keep each photo's own quality (estimated from its quantisation table, as
    ImageMagick does; 95 when it cannot be estimated).
    ``require_exif``: skip photos without EXIF (their corrected focal length could not be
    recorded for structure-from-motion). ``interpolation``: see :meth:`Undistortion.apply`.
    """

    barrel: Barrel | None = None
    camera: Camera | None = None
    crop: bool = False
    jpeg_quality: int | None = None
    require_exif: bool = True
    interpolation: str = "linear"

    def __post_init__(self) -> None:
        if (self.barrel is None) == (self.camera is None):
            raise InputError("CorrectionSpec needs exactly one of barrel= or camera=")
        q = self.jpeg_quality
        if q is not None:
            object.__setattr__(self, "jpeg_quality", validate.integer_in("jpeg_quality", q, 1, 100))

    def undistortion(self, width: int, height: int) -> Undistortion:
        """Tables for a ``width x height`` photo (a calibration is rescaled if the aspect matches)."""
        if self.barrel is not None:
            return Undistortion.for_barrel(self.barrel, width, height, crop=self.crop)
        cam = self.camera
        if (cam.width, cam.height) != (width, height):
            factor = width / cam.width
            if abs(cam.height * factor - height) > 0.5:
                raise DataError(f"photo is {width}x{height} but the calibration is {cam.width}x{cam.height} "
                                "(different aspect ratio)")
            cam = cam.scaled(factor)
        return Undistortion.for_camera(cam, crop=self.crop)


@dataclass(frozen=True)
class PhotoResult:
    """Outcome for one photo: ``output`` is None when it was skipped, ``error`` says why."""

    source: str
    output: str | None
    error: str | None = None
    output_camera: dict | None = None


@dataclass
class BatchReport:
    """What a batch did: corrected and skipped photos, wall time in seconds."""

    results: list[PhotoResult] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def written(self) -> list[PhotoResult]:
        return [r for r in self.results if r.output is not None]

    @property
    def skipped(self) -> list[PhotoResult]:
        return [r for r in self.results if r.output is None]

    def to_dict(self) -> dict:
        return {"written": len(self.written), "skipped": [{"photo": r.source, "reason": r.error}
                                                          for r in self.skipped],
                "seconds": self.seconds,
                "cameras": sorted({json.dumps(r.output_camera, sort_keys=True)
                                   for r in self.written if r.output_camera})}


def reason(exc: BaseException, source: str | os.PathLike) -> str:
    """``exc``'s message without a leading ``source: `` (callers print the name once)."""
    text = str(exc)
    for prefix in (f"{source}: ", f"{Path(source).name}: "):
        if text.startswith(prefix):
            return text[len(prefix):]
    return text


def list_photos(in_dir: str | os.PathLike) -> list[Path]:
    """JPEG photos directly inside ``in_dir``, sorted by name."""
    path = Path(in_dir)
    if not path.is_dir():
        raise InputError(f"input folder {str(path)!r} does not exist or is not a folder")
    return sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)


class _Worker:
    """Shared by the batch threads: the spec and remap tables cached per image size."""

    def __init__(self, spec: CorrectionSpec) -> None:
        self.spec = spec
        self.tables: dict[tuple[int, int], Undistortion] = {}
        self.metadata: dict[Path, PhotoMetadata] = {}  # read in decode(), used once in finish()
        self._tables_lock = threading.Lock()

    def tables_for(self, width: int, height: int) -> Undistortion:
        key = (width, height)
        with self._tables_lock:  # threads share the tables; build each size once
            if key not in self.tables:
                self.tables[key] = self.spec.undistortion(width, height)
            return self.tables[key]

    def decode(self, src: Path, colorspace: str = "BGRX") -> tuple[bytes, np.ndarray]:
        """The photo's bytes and its pixels, ``BGRX`` (H, W, 4) by default: OpenCV remaps
        4-channel pixels ~1.7x faster than 3-channel ones, and libjpeg-turbo writes and
        reads the padding byte at no cost."""
        data = src.read_bytes()
        if not data.rstrip(b"\x00").endswith(b"\xff\xd9"):
            raise DataError(f"{src}: corrupt JPEG (truncated: no end-of-image marker)")
        self.metadata[src] = read_metadata(data, str(src), require_exif=self.spec.require_exif)
        # libjpeg-turbo through simplejpeg in strict mode: damaged data raises with libjpeg's
        # own words instead of being printed on stderr and decoded into grey blocks (OpenCV).
        try:
            image = simplejpeg.decode_jpeg(data, colorspace=colorspace, strict=True)
        except ValueError as exc:
            raise DataError(f"{src}: corrupt JPEG ({exc})") from None
        return data, image

    def output_camera(self, src: Path, data: bytes, tables: Undistortion) -> dict:
        """Intrinsics of the corrected photo; the focal length comes from the calibration or,
        for a barrel model, from the photo's EXIF (None when EXIF lacks it)."""
        out = tables.output
        fx = fy = None
        meta = self.metadata.pop(src, None)
        if self.spec.camera is not None:
            fx, fy = out.fx, out.fy
        else:
            meta = meta or read_metadata(data, str(src), require_exif=False)
            try:
                raw_f = meta.focal_length_px(tables.source.width, tables.source.height)
                fx = fy = raw_f * tables.focal_scale
            except DataError:
                pass
        return {"width": out.width, "height": out.height, "fx_px": fx, "fy_px": fy,
                "cx_px": out.cx, "cy_px": out.cy, "focal_scale": tables.focal_scale}

    def finish(self, src: Path, dst: Path, data: bytes, corrected: np.ndarray, tables: Undistortion) -> PhotoResult:
        quality = self.spec.jpeg_quality or jpeg_quality(data) or 95
        sampling = simplejpeg.decode_jpeg_header(data)[3]  # the photo's own chroma subsampling
        encoded = simplejpeg.encode_jpeg(np.ascontiguousarray(corrected), quality,
                                         colorspace="BGRX" if corrected.shape[2] == 4 else "BGR",
                                         colorsubsampling=sampling if sampling in _SUBSAMPLING else "444")
        out = tables.output
        blob = transfer_metadata(data, encoded, focal_scale=tables.focal_scale,
                                 width=out.width, height=out.height, source=str(src))
        tmp = dst.with_name(dst.name + ".part")
        tmp.write_bytes(blob)
        os.replace(tmp, dst)
        return PhotoResult(str(src), str(dst), None, self.output_camera(src, data, tables))

    def __call__(self, job: tuple[Path, Path]) -> PhotoResult:
        src, dst = job
        try:
            data, image = self.decode(src)
            tables = self.tables_for(image.shape[1], image.shape[0])
            corrected = tables.apply(image, self.spec.interpolation)
            return self.finish(src, dst, data, corrected, tables)
        except (SkyfixError, OSError, cv2.error) as exc:
            self.metadata.pop(src, None)
            return PhotoResult(str(src), None, reason(exc, src))


def _threaded_results(worker: _Worker, jobs: list[tuple[Path, Path]], n_threads: int) -> Iterator[PhotoResult]:
    """Run ``worker`` over ``jobs`` on ``n_threads`` threads, at most two photos per thread in flight.

    OpenCV's decode, remap and encode release the GIL, so threads run in parallel while
    sharing one set of remap tables. Threads rather than forked processes: forking a
    process that already runs threads (a MAVLink reader, OpenCV's or torch's pools) can
    deadlock the child on a lock held at fork time.
    """
    with ThreadPoolExecutor(n_threads, thread_name_prefix="lens-correct") as pool:
        in_flight: set[Future[PhotoResult]] = set()
        for job in jobs:
            in_flight.add(pool.submit(worker, job))
            if len(in_flight) >= 2 * n_threads:
                done, in_flight = wait(in_flight, return_when=FIRST_COMPLETED)
                for future in done:
                    yield future.result()
        for future in as_completed(in_flight):
            yield future.result()


def correct_photos(photos: Iterable[str | os.PathLike], out_dir: str | os.PathLike, spec: CorrectionSpec, *,
                   workers: int | None = None, backend: str = "opencv", device: str | None = None,
                   batch_size: int = 8, progress: bool = True) -> BatchReport:
    """Correct ``photos`` into ``out_dir`` (same file names); never raises for one bad photo.

    ``workers``: threads (default: CPU count); with the OpenCV backend 1 runs in the calling
    thread. ``backend='torch'`` remaps batches of ``batch_size`` photos with kornia on
    ``device`` (default: CUDA when available, else CPU) while ``workers`` threads decode
    the next batch and encode the last (:mod:`skyfix.mapping.batch_torch`). Returns a :class:`BatchReport`;
    bad photos are logged at WARNING and listed in ``report.skipped``.
    """
    from skyfix.progress import bar as progress_bar

    if backend not in ("opencv", "torch"):
        raise InputError(f"backend must be 'opencv' or 'torch', got {backend!r}")
    if backend == "torch":
        from skyfix.mapping.remap_torch import require_torch

        require_torch()  # once, before any photo
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(Path(p), out / Path(p).name) for p in photos]
    for src, dst in jobs:
        if src.resolve() == dst.resolve():
            raise InputError(f"output folder {str(out)!r} is the input folder; refusing to overwrite {src.name}")
    n_workers = (os.cpu_count() or 1) if workers is None else int(validate.positive_scalar("workers", workers))
    report = BatchReport()
    start = time.perf_counter()
    bar = progress_bar(desc="lens correct", total=len(jobs), unit="photo", disable=not progress)
    try:
        if backend == "torch":
            from skyfix.mapping.batch_torch import torch_results

            results: Iterator[PhotoResult] = torch_results(_Worker(spec), jobs, device, batch_size,
                                                           min(n_workers, max(1, len(jobs))))
        elif n_workers <= 1 or len(jobs) <= 1:
            worker = _Worker(spec)
            results = (worker(job) for job in jobs)
        else:
            results = _threaded_results(_Worker(spec), jobs, min(n_workers, len(jobs)))
        for result in results:
            if result.error is not None:
                log.warning("skipped %s: %s", result.source, result.error)
            report.results.append(result)
            bar.update(1)
    finally:
        bar.close()
    report.results.sort(key=lambda r: r.source)
    report.seconds = time.perf_counter() - start
    return report
