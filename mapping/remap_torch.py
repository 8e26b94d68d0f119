"""Batched photo correction with torch/kornia, on a GPU when one is present.

Same tables and same geometry as :meth:`skyfix.mapping.correct.Undistortion.apply`
(bilinear, edge pixels replicated); results agree with OpenCV's remap (which interpolates
with 1/32-px fixed-point weights) to within rounding: mean difference < 0.2 grey level.

The sampling grid (the tables in grid_sample's normalised coordinates) is built once and
kept on the device; a batch costs one upload of uint8 pixels, one ``grid_sample`` and one
download of uint8 pixels (through page-locked host memory on CUDA, so the copies are DMA).
"""

from __future__ import annotations

import numpy as np

from skyfix.errors import InputError, NotAvailableError
from skyfix.mapping.correct import Undistortion

__all__ = ["TorchRemapper", "require_torch"]


def require_torch() -> None:
    """Raise :class:`NotAvailableError` (with the install advice of the README) unless torch
    and kornia import."""
    try:
        import kornia  # noqa: F401
        import torch  # noqa: F401
    except ImportError as exc:
        raise NotAvailableError(f"the torch backend needs torch and kornia ({exc.name or exc} is not installed): "
                                "install torch first (pip install torch; the CPU build where there is no GPU), "
                                "then the gpu extra (pip install -e '.[gpu]'), as the README says") from None


class TorchRemapper:
    """Apply one :class:`Undistortion` to batches ``(B, H, W[, C])`` of uint8 images.

    ``device``: a torch device string; default CUDA when available, else CPU. ``dtype``: the
    float type pixels and tables are interpolated in ("float32" or "float64").
    """

    def __init__(self, tables: Undistortion, device: str | None = None, dtype: str = "float32") -> None:
        require_torch()
        import torch
        from kornia.geometry.conversions import normalize_pixel_coordinates

        if dtype not in ("float32", "float64"):
            raise InputError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
        self._torch = torch
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        self.dtype = getattr(torch, dtype)
        self.tables = tables
        src = tables.source
        # Clamping the sample positions to the image is exactly edge replication; the grid is
        # normalised once (align_corners: -1 and +1 are the centres of the edge pixels).
        pixels_xy = np.stack((np.clip(tables.map_x, 0, src.width - 1), np.clip(tables.map_y, 0, src.height - 1)),
                             axis=-1).astype(np.float64)
        grid = normalize_pixel_coordinates(torch.from_numpy(pixels_xy), src.height, src.width)
        self._grid = grid.to(self.device, self.dtype)[None]  # (1, H_out, W_out, 2)
        self._pinned = self.device.type == "cuda"

    @property
    def output_shape(self) -> tuple[int, int]:
        """``(H_out, W_out)`` of the corrected images, pixels."""
        return int(self._grid.shape[1]), int(self._grid.shape[2])

    def _check(self, shape: tuple[int, ...], dtype: np.dtype) -> None:
        src = self.tables.source
        if dtype != np.uint8 or len(shape) not in (3, 4) or tuple(shape[1:3]) != (src.height, src.width):
            raise InputError(f"images must be uint8 (B, {src.height}, {src.width}[, C]), got {dtype} {tuple(shape)}")

    def remap_tensor(self, batch_u8):
        """Corrected uint8 tensor ``(B, H_out, W_out, C)`` from a uint8 tensor ``(B, H, W, C)``
        on this remapper's device (channels last, as decoders write pixels)."""
        import torch.nn.functional as F

        torch = self._torch
        x = batch_u8.permute(0, 3, 1, 2).to(self.dtype)
        with torch.no_grad():
            out = F.grid_sample(x, self._grid.expand(x.shape[0], -1, -1, -1), mode="bilinear",
                                padding_mode="border", align_corners=True)
        return out.round_().clamp_(0, 255).to(torch.uint8).permute(0, 2, 3, 1)

    def remap_images(self, images: list[np.ndarray]) -> np.ndarray:
        """Corrected batch ``(B, H_out, W_out, C)`` uint8 from ``B`` images ``(H, W, C)`` of one
        size. On CUDA the result lives in page-locked host memory (a view of a torch
        tensor, kept alive by the array): encoders may read it directly."""
        torch = self._torch
        if not images:
            raise InputError("remap_images needs at least one image")
        first = np.asarray(images[0])
        self._check((len(images), *first.shape), first.dtype)
        if first.ndim != 3 or any(np.asarray(im).shape != first.shape or np.asarray(im).dtype != np.uint8
                                  for im in images):
            raise InputError(f"images must all be uint8 {first.shape} with a channel axis")
        n = len(images)
        host_in = torch.empty((n, *first.shape), dtype=torch.uint8, pin_memory=self._pinned)
        staging = host_in.numpy()
        for i, im in enumerate(images):
            staging[i] = im
        out = self.remap_tensor(host_in.to(self.device, non_blocking=self._pinned))
        host_out = torch.empty(tuple(out.shape), dtype=torch.uint8, pin_memory=self._pinned)
        host_out.copy_(out, non_blocking=self._pinned)
        if self._pinned:
            torch.cuda.current_stream(self.device).synchronize()
        return host_out.numpy()

    def __call__(self, images: np.ndarray) -> np.ndarray:
        """Corrected uint8 batch ``(B, H_out, W_out[, C])``."""
        batch = np.asarray(images)
        self._check(batch.shape, batch.dtype)
        gray = batch.ndim == 3
        out = self.remap_images(list(batch[..., None] if gray else batch))
        return out[..., 0] if gray else out
