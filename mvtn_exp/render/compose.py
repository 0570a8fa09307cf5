"""The images of a render call from its active pixels: every group's ``(pix, rgb, alpha)`` written
into dense channel-first images and alpha (background and 0 elsewhere), as an autograd function."""
from __future__ import annotations

import torch


def _channel_base(pix: torch.Tensor, HW: int) -> torch.Tensor:
    """Flat pixel ``[P]`` (image i, pixel p) -> flat index of its channel 0 in ``[N, 3, HW]`` images:
    (3 i + c) HW + p = pix + 2 i HW + c HW, channel c at ``+ c * HW``."""
    return pix + 2 * HW * torch.div(pix, HW, rounding_mode="floor")


class Compose(torch.autograd.Function):
    """Active pixels of the groups -> dense images ``[N, 3, H, W]`` (background elsewhere) and alpha
    ``[N, 1, H, W]`` (0 elsewhere), N = B * M. Called as ``apply(background, N, HW, pix_1, rgb_1,
    alpha_1, pix_2, ...)``: per group flat pixel indices ``[P_g]`` (into the whole batch), rgb
    ``[P_g, 3]``, alpha ``[P_g]``, written straight into the images (no concatenated copy). The
    backward pass gathers the images' gradient at the active pixels: it keeps only the ``pix``
    (8 bytes per active pixel)."""

    @staticmethod
    def forward(ctx, background, N: int, HW: int, *parts):
        ref = parts[1]
        img = torch.empty(N, 3, HW, dtype=ref.dtype, device=ref.device)
        img.copy_(background.to(ref.dtype)[:, None].expand(N, 3, HW))
        a = torch.zeros(N * HW, dtype=ref.dtype, device=ref.device)
        flat = img.view(-1)
        for pix, rgb, alpha in zip(parts[0::3], parts[1::3], parts[2::3]):
            base = _channel_base(pix, HW)
            for c in range(3):
                flat.index_copy_(0, base + c * HW, rgb[:, c])
            a.index_copy_(0, pix, alpha)
        ctx.save_for_backward(*parts[0::3])
        ctx.HW = HW
        return img, a

    @staticmethod
    def backward(ctx, g_img, g_alpha):
        HW = ctx.HW
        flat, g_a = g_img.reshape(-1), g_alpha.reshape(-1)
        grads = [None, None, None]
        for pix in ctx.saved_tensors:
            base = _channel_base(pix, HW)
            grads += [None, torch.stack([flat.index_select(0, base + c * HW) for c in range(3)], 1), g_a.index_select(0, pix)]
        return tuple(grads)
