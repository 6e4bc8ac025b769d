"""Procedural rectified stereo scenes with exact ground truth, rendered with torch on any device.

A scene is a background plane plus many foreground surfaces. Each surface is a patch of disparity
``d(x, y) = a*x + b*y + c`` (slanted or fronto-parallel), optionally curved by a quadratic term
(``curve_probability``: domes, bowls, saddles, cylinders), cut to a random shape (star polygon:
triangles to 8-gons and stars, near-ellipses, thin bars; optionally with an elliptic hole) and
painted with a texture attached to the surface (options aimed at hard cases: thin structures, flat
planes, repetitive patterns, wide disparity ranges, drawn in `hard_cases`). Both views are
rendered exactly: in each view, every pixel shows the surface with the largest disparity there
(z-buffer). A right pixel ``x_r`` sees surface S at the left coordinate ``x_l`` solving
``x_l - d_S(x_l, y) = x_r`` (for a plane ``x_l = (x_r + b*y + c) / (1 - a)``; for a curved surface
the root of a quadratic), and shows S's texture at ``(x_l, y)``; so warping the right view by the
left ground truth reproduces the left view wherever the match is visible.

Coordinates: x to the right, y down, in pixels of the output images, pixel centres at integers.
Disparity is positive, in pixels of the LEFT view: left pixel (x, y) matches right pixel (x - d, y).

Randomness comes only from a ``torch.Generator`` on the target device seeded by ``generate``'s
``seed``: a (config, device, batch_size, seed) tuple gives the same batch bit for bit. CPU and CUDA
generators differ, so a seed gives different scenes on different device types.

The modules, in the order a batch is made:

    config         SceneConfig, PhotometricConfig: what is drawn
    draw           Draw: the one source of randomness
    sampling       draw_scenes: each surface's shape, disparity, look and lighting, as a Scene
    hard_cases     thin, flat and repetitive surfaces, wide disparity ranges
    layouts        road and room layouts (a ground plane seen in perspective)
    textures       the texture banks
    scene          Scene (the drawn parameters) and SyntheticBatch (the rendered pairs)
    geometry       a surface's disparity, gradient and shape at a point
    visibility     the z-buffer: which surface each sample sees
    shading        the colour a view sees there
    rectification  the right view's rows moved off the left's (an imperfect rectification)
    photometric    blur, gamma, vignetting, gain, offset, noise, JPEG after rendering
    generator      SceneGenerator: all of the above on one device
"""

from .config import PhotometricConfig, SceneConfig
from .generator import SceneGenerator
from .scene import MAX_SIDES, Scene, SyntheticBatch

__all__ = ["MAX_SIDES", "PhotometricConfig", "SceneConfig", "Scene", "SyntheticBatch", "SceneGenerator"]
