"""CREStereo++ and Lite-CREStereo++ in plain PyTorch: the network, one block of the paper per
file, and its weights file. Running it on images of any size is ``crestereo_pp.inference``'s.

Disparity is positive everywhere, in pixels of the left image (the right match is at x - d).

    from crestereo_pp.model import CREStereoPP, ModelConfig
    network = CREStereoPP(ModelConfig.preset("lite"))
    out = network(left, right)                      # (B, 3, H, W) in [0, 255], H, W multiples of 32
    out.disparity, out.uncertainty                  # (B, 1, H, W) each
"""

from .config import ModelConfig
from .network import CREStereoPP, NetworkOutput, padded_size

__all__ = [
    "CREStereoPP",
    "ModelConfig",
    "NetworkOutput",
    "padded_size",
]
