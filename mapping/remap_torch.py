"""Batched photo correction with torch/kornia, on a GPU when one is present.

Same tables and same geometry as :meth:`skyfix.mapping.correct.Undistortion.apply`
(bilinear, edge pixels replicated); results agree with OpenCV's fixed-point remap to
within one grey level.
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

        if dtype not in ("float32", "float64"):
            raise InputError(f"dtype must be 'float32' or 'float64', got {dtype!r}")
        self._torch = torch
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        self.dtype = getattr(torch, dtype)
        self.tables = tables
        self._map_x = torch.from_numpy(np.array(tables.map_x)).to(self.device, self.dtype)[None]
        self._map_y = torch.from_numpy(np.array(tables.map_y)).to(self.device, self.dtype)[None]

    def __call__(self, images: np.ndarray) -> np.ndarray:
        """Corrected uint8 batch ``(B, H_out, W_out[, C])``."""
        from kornia.geometry.transform import remap

        torch = self._torch
        batch = np.asarray(images)
        src = self.tables.source
        if batch.dtype != np.uint8 or batch.ndim not in (3, 4) or batch.shape[1:3] != (src.height, src.width):
            raise InputError(f"images must be uint8 (B, {src.height}, {src.width}[, C]), got "
                             f"{batch.dtype} {batch.shape}")
        gray = batch.ndim == 3
        x = torch.from_numpy(batch[..., None] if gray else batch).to(self.device)
        x = x.permute(0, 3, 1, 2).to(self.dtype)
        n = x.shape[0]
        # Clamping the sample positions to the image is exactly edge replication.
        map_x = self._map_x.clamp(0, src.width - 1).expand(n, -1, -1)
        map_y = self._map_y.clamp(0, src.height - 1).expand(n, -1, -1)
        with torch.no_grad():
            out = remap(x, map_x, map_y, mode="bilinear", padding_mode="border", align_corners=True)
        out = out.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
        return out[..., 0] if gray else out
