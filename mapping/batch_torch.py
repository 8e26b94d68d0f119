"""The torch backend of :func:`skyfix.mapping.batch.correct_photos`: decode, remap and encode
overlapped across photos.

Worker threads decode (libjpeg-turbo through simplejpeg releases the GIL) and encode;
the calling thread gathers each batch of decoded photos, remaps it on the device in one
``grid_sample`` (:class:`~skyfix.mapping.remap_torch.TorchRemapper`, grid built once per
photo size and kept on the device) and hands the corrected pixels back to the threads to
encode. The next batch's photos are queued for decoding before a batch is remapped, so
the threads decode batch k+1 and encode batch k while the device remaps: the correction
then costs the decode+encode floor plus whatever the calling thread adds.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from skyfix.errors import SkyfixError

if TYPE_CHECKING:
    from skyfix.mapping.batch import PhotoResult, _Worker
    from skyfix.mapping.remap_torch import TorchRemapper

__all__ = ["torch_results"]

_ERRORS = (SkyfixError, OSError, cv2.error)
Decoded = tuple[Path, Path, bytes, np.ndarray]


def _decode(worker: _Worker, job: tuple[Path, Path]) -> Decoded | PhotoResult:
    from skyfix.mapping.batch import PhotoResult, reason

    src, dst = job
    try:
        data, image = worker.decode(src, "BGR")
    except _ERRORS as exc:
        worker.metadata.pop(src, None)
        return PhotoResult(str(src), None, reason(exc, src))
    return src, dst, data, image


def _finish(worker: _Worker, item: Decoded, corrected: np.ndarray, tables) -> PhotoResult:
    from skyfix.mapping.batch import PhotoResult, reason

    src, dst, data, _ = item
    try:
        return worker.finish(src, dst, data, corrected, tables)
    except _ERRORS as exc:
        return PhotoResult(str(src), None, reason(exc, src))


def _remap_batch(worker: _Worker, remappers: dict[tuple[int, int], TorchRemapper], items: list[Decoded],
                 device: str | None) -> Iterator[tuple[Decoded, np.ndarray | None, object, str | None]]:
    """Each decoded photo with its corrected pixels (None and the reason when its size's tables
    or the remap failed), one device call per photo size in the batch."""
    from skyfix.mapping.batch import reason
    from skyfix.mapping.remap_torch import TorchRemapper

    by_size: dict[tuple[int, int], list[Decoded]] = {}
    for item in items:
        by_size.setdefault(item[3].shape[:2], []).append(item)
    for (h, w), group in by_size.items():
        try:
            tables = worker.tables_for(w, h)
            if (w, h) not in remappers:
                remappers[(w, h)] = TorchRemapper(tables, device=device)
            corrected = remappers[(w, h)].remap_images([it[3] for it in group])
        except _ERRORS as exc:
            for it in group:
                worker.metadata.pop(it[0], None)
                yield it, None, None, reason(exc, it[0])
            continue
        for it, out in zip(group, corrected, strict=True):
            yield it, out, tables, None


def torch_results(worker: _Worker, jobs: list[tuple[Path, Path]], device: str | None, batch_size: int,
                  n_threads: int) -> Iterator[PhotoResult]:
    """Correct ``jobs`` ((source, destination) pairs) with ``n_threads`` decode/encode threads
    and the remap on ``device`` in batches of ``batch_size`` photos; results in completion
    order. At most three batches are in flight (one decoding, one remapping, one encoding)."""
    from skyfix.mapping.batch import PhotoResult

    remappers: dict[tuple[int, int], TorchRemapper] = {}
    batches = [jobs[i:i + batch_size] for i in range(0, len(jobs), batch_size)]
    with ThreadPoolExecutor(max(1, n_threads), thread_name_prefix="lens-torch") as pool:
        decoding: deque[list[Future]] = deque()
        encoding: deque[Future[PhotoResult]] = deque()
        for k, _ in enumerate(batches):
            while len(decoding) < 2 and k + len(decoding) < len(batches):  # this batch and the next
                decoding.append([pool.submit(_decode, worker, job) for job in batches[k + len(decoding)]])
            decoded = [f.result() for f in decoding.popleft()]
            yield from (d for d in decoded if isinstance(d, PhotoResult))
            items = [d for d in decoded if not isinstance(d, PhotoResult)]
            for item, out, tables, why in _remap_batch(worker, remappers, items, device):
                if out is None:
                    yield PhotoResult(str(item[0]), None, why)
                else:
                    encoding.append(pool.submit(_finish, worker, item, out, tables))
            while len(encoding) > batch_size or (encoding and encoding[0].done()):
                yield encoding.popleft().result()
        while encoding:
            yield encoding.popleft().result()
