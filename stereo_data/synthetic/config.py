"""What the procedural scenes draw (`SceneConfig`) and how their views are changed after rendering
(`PhotometricConfig`)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class PhotometricConfig:
    """Random photometric changes, drawn independently for each view and applied after rendering,
    in this order: Gaussian blur, gamma, vignetting, gain, offset, Gaussian noise, clipping to
    [0, 255], JPEG compression."""

    blur_probability: float = 0.3
    blur_sigma: tuple[float, float] = (0.3, 1.2)  # px
    gamma: tuple[float, float] = (0.75, 1.35)  # out = 255 * (in / 255) ** gamma
    gain: tuple[float, float] = (0.7, 1.3)  # multiplies all channels
    channel_gain: tuple[float, float] = (0.9, 1.1)  # multiplies each channel on top of gain
    offset: tuple[float, float] = (-15.0, 15.0)  # grey levels added
    noise_sigma: tuple[float, float] = (0.0, 4.0)  # grey levels, per pixel and channel
    vignetting: float = 0.0  # at most this share of the light lost at the frame's corners (off: 0)
    jpeg_probability: float = 0.0  # views saved as JPEG and read back (compression artefacts)
    jpeg_quality: tuple[int, int] = (40, 95)  # JPEG quality, uniform

    def __post_init__(self) -> None:
        if not 0.0 <= self.vignetting < 1.0:
            raise ValueError(f"vignetting must be in [0, 1), got {self.vignetting}")
        if not 0.0 <= self.jpeg_probability <= 1.0:
            raise ValueError(f"jpeg_probability must be in [0, 1], got {self.jpeg_probability}")
        if not 1 <= self.jpeg_quality[0] <= self.jpeg_quality[1] <= 100:
            raise ValueError(f"jpeg_quality must be 1 <= low <= high <= 100, got {self.jpeg_quality}")


@dataclass(frozen=True)
class SceneConfig:
    """What the generator draws. Lengths are in output pixels unless said otherwise.

    Anti-aliasing: with ``supersample`` k > 1 each pixel's colour is the mean of a k x k grid of
    point samples spread evenly over its area (as a camera integrates light over a pixel): edges get
    partial-coverage pixels and texels finer than a pixel are averaged, not aliased. The ground truth
    (disparity, occlusion) stays the point value at the pixel centre.

    Curved surfaces: with ``curve_probability`` a foreground surface's disparity gets a quadratic
    term about its centre, ``delta * (l1 * p1**2 + l2 * p2**2) / R**2`` with p1, p2 the point's
    coordinates along two random perpendicular axes, R the shape's extent, l1, l2 in [-1, 1] (same
    signs: a dome or a bowl; opposite: a saddle; one near zero: a cylinder) and delta px the bulge.
    The plane's slope and span are shrunk so that the surface still keeps |grad d| <= max_slope and
    its disparity range within the shape.

    Lighting: with ``lighting_probability`` a scene is lit by a directional light: each surface
    point's colour is scaled by ambient + (1 - ambient) * max(0, n . L), its normal n following its
    disparity gradient (so curved surfaces shade smoothly, slanted ones by their slant), the same in
    both views. With ``specular_probability`` surfaces of lit scenes also get a Blinn-Phong highlight
    towards each camera: the right camera sits to the right, so a highlight lies elsewhere on the
    surface in each view (real glossy surfaces break matching so). The ground truth is unchanged.

    Road scenes: with ``road_probability`` a scene is laid out as driving scenes are: a ground plane
    receding to a horizon (a strong vertical disparity gradient), a far and weakly textured sky
    above it, and the foreground surfaces standing on the ground (each at least as near as the
    ground at its centre row); the ground's texture is seen in perspective (see `layouts.Road`).

    Room scenes: with ``room_probability`` a scene is laid out as indoor scenes are: a back wall
    (fronto-parallel, at 10-45 % of the maximum disparity, textured as any surface) and a floor
    meeting it along a line a quarter to nine tenths down the frame, nearing the camera below it;
    the floor's texture is seen in perspective as a road's ground is, and the foreground surfaces
    stand on the floor in front of the wall.

    Hard cases (`hard_cases` has their ranges), each off at 0:
    - ``thin_probability``: foreground surfaces that are thin structures (wires, stems, pipes, chair
      legs): bars 1-6 px wide and 0.2-1 frame widths long, often crossing, with their disparity in the
      nearer half of [the background's highest, max_disparity]: in front of the background by at
      least (1 - background_max_fraction) / 2 of the largest disparity (in road and room scenes: of
      the ground under their centre).
    - ``flat_probability``: surfaces (of those not thin; the background too) that are large weakly
      textured planes (walls, tables, floors): 0.5-1 frame widths across, texture std 1-4 grey
      levels, a brightness ramp of a third to all of ``shading`` across them, never curved.
    - ``repetitive_probability``: foreground surfaces (of those not flat) painted with a periodic
      pattern (stripes, checkers, grid lines or dots) of period 4-40 px repeating along the rows
      (turned by at most 10 degrees): ambiguous matches one period apart, which the surface's
      outline resolves. Never the background: covering the frame, it would match itself a period
      away everywhere but at the left border, and no matcher could find its disparity.
    - ``wide_range_probability``: scenes whose largest disparity is drawn uniformly in
      [max_disparity, wide_max_disparity] instead of max_disparity.
    - ``reflective_probability``: foreground surfaces (of those not thin) that reflect a farther
      scene (car bodies and windows, glossy floors, glass): a second texture of std 4-40 grey
      levels laid over their own, whose disparity is a share of 0-0.8 of theirs, so that it moves
      between the views less than the surface does. The ground truth stays the surface's; its
      outline tells it apart. Never the background, which no outline would tell apart.

    Imperfect rectification: with ``row_offset_probability`` a pair's right view is moved off the
    left's rows after rendering (before the photometric changes) by a plane of vertical offsets
    dy = centre + across * (x / W - 1/2) + down * (y / H - 1/2), each term uniform in
    +-row_offset / 2, so that |dy| <= row_offset px everywhere (`rectification`). Vertical only: the
    horizontal ground truth stays exact.

    Scale/crop augmentation: each scene is magnified by a random ``s = 2**U(log2_scale)``: every
    length (shape sizes, bar widths, texel sizes) is its unscaled length times s. A random crop of a
    procedural scene is distributed like the scene itself, so the crop is implicit: shapes are
    spread over the output frame (and a margin of 10 % around it) at every scale. Disparities are
    drawn in output pixels after scaling, so that they span [0, max_disparity] at every scale.
    """

    height: int = 384
    width: int = 512
    max_disparity: float | None = None  # px; None means 192 * width / 512
    wide_max_disparity: float | None = None  # px, wide-range scenes; None means max(max_disparity, 256 * width / 512)
    surfaces: int = 24  # foreground surface slots per scene
    min_surfaces: int = 8  # a scene uses U{min_surfaces..surfaces} of them
    size: tuple[float, float] = (0.02, 0.35)  # unscaled shape radius / width, log-uniform
    bar_probability: float = 0.15  # thin bars: 2-8 px wide, 0.2-1 width long (unscaled)
    round_probability: float = 0.3  # near-ellipses; the others are 3- to 8-gons
    star_probability: float = 0.5  # polygons with random vertex radii (irregular, concave)
    hole_probability: float = 0.2
    slant_probability: float = 0.7  # the others are fronto-parallel
    max_slope: float = 0.4  # bound on |grad d| (px of disparity per px); must be < 1
    background_max_fraction: float = 0.5  # the background's disparity stays below this * max
    texture_size: int = 256  # texels per side of each (periodic) texture
    noise_textures: int = 4  # 1/f^alpha noise: photo-like, fine detail, smooth gradients
    leaves_textures: int = 2  # dead leaves: random discs with sharp edges, scale invariant
    pattern_textures: int = 2  # stripes, checkers, grids, dots
    photo_textures: int = 0  # crops of photographs (stereo_data.photos; needs scikit-image)
    texel_size: tuple[float, float] = (1.2, 5.0)  # unscaled px per texel, log-uniform
    contrast: tuple[float, float] = (6.0, 100.0)  # grey-level std of a surface's texture, log-uniform
    shading: float = 60.0  # at most this many grey levels of linear ramp across a surface
    log2_scale: tuple[float, float] = (-0.2, 0.4)
    curve_probability: float = 0.0  # foreground surfaces that are curved (quadric disparity); the others planar
    lighting_probability: float = 0.0  # scenes lit by a directional light (shading by surface orientation)
    specular_probability: float = 0.0  # surfaces of lit scenes with highlights, which differ between the views
    road_probability: float = 0.0  # scenes laid out as a road under a sky (see `layouts.Road`); the others as before
    room_probability: float = 0.0  # scenes laid out as a room: a floor meeting a back wall (not road scenes)
    thin_probability: float = 0.0  # foreground surfaces that are thin structures near the camera
    flat_probability: float = 0.0  # surfaces that are large weakly textured planes with slow shading
    repetitive_probability: float = 0.0  # surfaces painted with a pattern repeating every 4-40 px along the rows
    wide_range_probability: float = 0.0  # scenes whose largest disparity is drawn up to wide_max_disparity
    reflective_probability: float = 0.0  # foreground surfaces reflecting a farther scene over their own texture
    row_offset_probability: float = 0.0  # pairs whose right view's rows are off the left's (vertical offsets)
    row_offset: float = 2.0  # px: the largest vertical offset of such a pair, anywhere in the frame
    supersample: int = 1  # anti-aliasing: images are the mean of supersample x supersample samples per pixel
    photometric: PhotometricConfig | None = field(default_factory=PhotometricConfig)

    def __post_init__(self) -> None:
        max_disparity = 192.0 * self.width / 512.0 if self.max_disparity is None else self.max_disparity
        object.__setattr__(self, "max_disparity", max_disparity)
        wide_max = self.wide_max_disparity
        wide_max = max(max_disparity, 256.0 * self.width / 512.0) if wide_max is None else wide_max
        object.__setattr__(self, "wide_max_disparity", wide_max)
        if self.height < 1 or self.width < 1:
            raise ValueError(f"image size must be positive, got {self.height}x{self.width}")
        if not 0 < max_disparity:
            raise ValueError(f"max_disparity must be positive, got {max_disparity}")
        if self.wide_range_probability > 0 and not wide_max >= max_disparity:
            raise ValueError(f"wide_max_disparity must be at least max_disparity, got {wide_max}")
        if not 0 <= self.max_slope < 1:
            raise ValueError("max_slope must be in [0, 1): the right view needs 1 - a > 0")
        if not 1 <= self.min_surfaces <= self.surfaces:
            raise ValueError("need 1 <= min_surfaces <= surfaces")
        if any(low > high for low, high in (self.log2_scale, self.size, self.texel_size)):
            raise ValueError("ranges must be (low, high)")
        if self.texture_count < 1:
            raise ValueError("need at least one texture")
        for name in (
            "road_probability",
            "room_probability",
            "curve_probability",
            "lighting_probability",
            "specular_probability",
            "thin_probability",
            "flat_probability",
            "repetitive_probability",
            "wide_range_probability",
            "reflective_probability",
            "row_offset_probability",
        ):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not 0.0 <= self.row_offset <= 8.0:
            raise ValueError(f"row_offset must be in [0, 8] px, got {self.row_offset}")
        if self.supersample < 1:
            raise ValueError(f"supersample must be a positive integer, got {self.supersample}")
        if 2 ** self.log2_scale[0] * self.texel_size[0] * self.supersample < 1:
            raise ValueError("the smallest texel must cover at least one sample: 1 / supersample px (aliasing)")

    @property
    def texture_count(self) -> int:
        return self.noise_textures + self.leaves_textures + self.pattern_textures + self.photo_textures
