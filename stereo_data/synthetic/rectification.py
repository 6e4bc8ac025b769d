"""An imperfect rectification (``SceneConfig.row_offset_probability``): the right view's rows moved
off the left's by a plane of vertical offsets, as a real rig's residual rotation or focal length
mismatch leaves them (CREStereo trained its correlation's 2D search so). The offsets are vertical
only, so the horizontal ground truth stays exact."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from .config import SceneConfig
from .draw import Draw


def draw_row_offsets(batch_size: int, cfg: SceneConfig, draw: Draw) -> torch.Tensor:
    """(B, 3) float32 planes (centre, across, down) px: the right view's match of a left pixel lies

        dy(x, y) = centre + across * (x / W - 1/2) + down * (y / H - 1/2)

    px lower than its row (the convention of `inference.row_alignment.RowOffset`). A share
    ``row_offset_probability`` of the pairs is drawn off its rows: centre, across and down uniform
    in +-row_offset / 2, so that |dy| stays within ``row_offset`` px everywhere; the others are zero."""
    half = cfg.row_offset / 2
    planes = draw.uniform((batch_size, 3), -half, half)
    return planes * draw.chance((batch_size, 1), cfg.row_offset_probability)


def offset_rows(image: torch.Tensor, planes: torch.Tensor) -> torch.Tensor:
    """``image`` (B, C, H, W) in [0, 255] with each sample's content moved down by its plane's dy (B, 3), px
    (`draw_row_offsets`): the result at (x, y) is the image at (x, y - dy(x, y)), bilinear, its
    edge rows repeated where that lies outside the frame. Samples whose plane is zero come back
    as they were."""
    batch, _, height, width = image.shape
    x = torch.arange(width, device=image.device, dtype=torch.float32).view(1, 1, -1)
    y = torch.arange(height, device=image.device, dtype=torch.float32).view(1, -1, 1)
    centre, across, down = (planes[:, k].view(-1, 1, 1).to(torch.float32) for k in range(3))
    dy = centre + across * (x / width - 0.5) + down * (y / height - 0.5)  # (B, H, W)
    source_y = (y - dy).clamp(0, height - 1)
    grid = torch.stack([2 * x.expand_as(dy) / max(width - 1, 1) - 1, 2 * source_y / max(height - 1, 1) - 1], -1)
    moved = F.grid_sample(image, grid.to(image.dtype), mode="bilinear", padding_mode="border", align_corners=True)
    still = (planes == 0).all(-1).view(-1, 1, 1, 1)
    return torch.where(still, image, moved.clamp(0, 255))
