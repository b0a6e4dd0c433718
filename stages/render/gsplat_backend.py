"""Optional GPU rendering through gsplat, used when CUDA and gsplat are both present.

Never required: goi's CPU rasteriser has the same semantics, and the tests run without a GPU.
The backend is handed to a `Rasterizer` (`Rasterizer(..., backend=auto_backend())`); the
rasteriser itself never imports this module.
"""

from __future__ import annotations

import importlib.util

import numpy as np

from stages.render.composite import Rendered
from stages.render.constants import NEAR
from stages.render.rasterizer import Rasterizer, RenderBackend
from stages.scene.cameras import Camera

# Channel counts gsplat's CUDA kernels are compiled for; other widths are padded up.
_GSPLAT_CHANNELS = (1, 2, 3, 4, 5, 8, 9, 16, 17, 32, 33, 64, 65, 128, 129, 256, 257, 512, 513)


def gsplat_available() -> bool:
    if importlib.util.find_spec("gsplat") is None:
        return False
    import torch

    return bool(torch.cuda.is_available())


def auto_backend() -> RenderBackend | None:
    """gsplat when it can run here, else None (the CPU path)."""
    return GsplatBackend() if gsplat_available() else None


def padded_channels(n: int) -> int:
    return next((c for c in _GSPLAT_CHANNELS if c >= n), n)


class GsplatBackend:
    name = "gsplat"

    def render(
        self,
        rast: Rasterizer,
        cam: Camera,
        values: np.ndarray | None = None,
        background: np.ndarray | None = None,
    ) -> Rendered:
        """RGB from SH (values None) or per-Gaussian values [N, C] composited by gsplat."""
        import torch
        from gsplat import rasterization

        dev = torch.device("cuda")

        def t(a: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(a)).to(dev)

        keep = rast.valid
        viewmat = np.eye(4, dtype=np.float32)
        viewmat[:3, :3], viewmat[:3, 3] = cam.R, cam.t
        K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], np.float32)
        kwargs: dict = {}
        if values is None:
            colors = t(rast.sh[keep])  # [N, K, 3]
            kwargs["sh_degree"] = int(round(np.sqrt(rast.sh.shape[1]))) - 1
            if background is not None:
                kwargs["backgrounds"] = t(np.asarray(background, np.float32)[None])
            n_ch = 3
        else:
            n_ch = values.shape[1]
            pad = np.zeros((int(keep.sum()), padded_channels(n_ch)), np.float32)
            pad[:, :n_ch] = values[keep]
            colors = t(pad)
        with torch.no_grad():
            img, alpha, _ = rasterization(
                t(rast.means[keep]),
                t(rast.quats[keep]),
                t(rast.scales[keep]),
                t(rast.opacities[keep]),
                colors,
                t(viewmat[None]),
                t(K[None]),
                cam.width,
                cam.height,
                near_plane=NEAR,
                render_mode="RGB+ED",
                packed=False,
                **kwargs,
            )
        img = img[0].cpu().numpy()
        depth = img[..., -1]
        return Rendered(img[..., :n_ch].copy(), alpha[0, ..., 0].cpu().numpy(), depth.copy())
