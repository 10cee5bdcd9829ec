"""Training pairs for the learned descriptor: two renderings of a procedural object.

:func:`render_pair` renders a :func:`~poseflow.features.procedural.random_mesh` with a
:func:`~poseflow.features.procedural.random_texture` twice with poseflow's ray caster, from
viewpoints that differ by up to ``max_view_angle`` plus an arbitrary in-plane roll, each at its
own scale, light, background, optional clutter object, blur and noise, each cropped exactly as
FunFlow6D crops a target; in half of the pairs view A is rendered the way the query's views are
(black background, headlight, the lifting's crop). Its ground-truth correspondences come from the
depth: every object pixel of crop A is lifted to the model frame, projected into view B and kept
where B's depth agrees. :class:`PairGenerator` streams seeded batches (:class:`PairBatch`) of them.
For a depth-aware descriptor each view also carries its
:func:`~poseflow.features.learned.depth_layers`, from depth corrupted by the sensor model
(:class:`~poseflow.data.DepthNoise`) unless the view is rendered in the query's style.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as F

from poseflow.data.depth_noise import DepthNoise
from poseflow.errors import DegenerateInputError
from poseflow.features.learned import depth_layers
from poseflow.features.lifting import jitter_boxes
from poseflow.geometry.pointcloud import crop_box_around, crop_resize, pixels_to_crop

__all__ = [
    "PairBatch",
    "PairGenerator",
    "ViewPair",
    "render_pair",
]

from poseflow.features.procedural import (
    SolidTexture,
    mix_colors,
    random_color,
    random_direction,
    random_mesh,
    random_texture,
    texture_images,
    value_noise,
)
from poseflow.geometry.se3 import axis_angle_to_rotation, quaternion_to_rotation
from poseflow.render.mesh import TexturedMesh
from poseflow.render.raycast import Light, Renderer, RenderOutput


@dataclass
class ViewPair:
    """Two crops of one procedural object and their ground-truth correspondences.

    Attributes:
        images: the crops ``(2, C, S, S)`` in ``[0, 1]``, float32: RGB, and with ``depth``
            the depth layers (``C = 5``).
        coords: each crop pixel's model point ``(2, S, S, 3)`` in diameters (0 off the object).
        mask: crop pixels showing the object ``(2, S, S)`` bool.
        uv_a: object pixels of crop A ``(P, 2)`` (crop coordinates, pixel centres).
        uv_b: their matches in crop B ``(P, 2)`` (sub-pixel crop coordinates).
        points: their model points ``(P, 3)`` in diameters.
        styled: whether each view is rendered in the query's style (no colour jitter then).
    """

    images: torch.Tensor
    coords: torch.Tensor
    mask: torch.Tensor
    uv_a: torch.Tensor
    uv_b: torch.Tensor
    points: torch.Tensor
    styled: tuple[bool, bool] = (False, False)


def _background(rng: np.random.Generator, side: int, images: Sequence[np.ndarray]) -> np.ndarray:
    """A random background ``(side, side, 3)`` float32 in ``[0, 1]``."""
    kind = rng.random()
    if kind < 0.25:
        bg = np.broadcast_to(random_color(rng), (side, side, 3)).copy()
    elif kind < 0.5:
        noise = value_noise(rng, float(rng.uniform(1.0, 6.0)))
        yy, xx = np.mgrid[0:side, 0:side] / side - 0.5
        t = noise(np.stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)], axis=1))
        bg = mix_colors(random_color(rng), random_color(rng), t).reshape(side, side, 3)
    else:
        from PIL import Image

        src = images[int(rng.integers(len(images)))]
        h, w = src.shape[:2]
        c = int(rng.integers(max(8, min(h, w) // 4), min(h, w) + 1))
        y0, x0 = int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1))
        patch = Image.fromarray(src[y0 : y0 + c, x0 : x0 + c]).resize((side, side))
        bg = np.asarray(patch, dtype=np.float32) / 255.0
        bg = bg * rng.uniform(0.4, 1.0) + rng.uniform(0, 0.3)
    return np.clip(bg, 0, 1).astype(np.float32)


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur of ``(3, H, W)``."""
    r = max(1, math.ceil(2.5 * sigma))
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    out = F.conv2d(F.pad(img[:, None], (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    out = F.conv2d(F.pad(out, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return out[:, 0]


def _shade(
    rng: np.random.Generator,
    out: RenderOutput,
    poses: np.ndarray,
    K: np.ndarray,
    textures: Sequence[SolidTexture],
    diameters: Sequence[float],
    background: np.ndarray,
    *,
    headlight: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Colour image ``(H, W, 3)`` and object-0 model coordinates ``(H, W, 3)`` (in diameters).

    ``headlight``: the renderer's default light (as the query's renderings are lit) instead of a
    random one.
    """
    depth = out.depth.numpy().astype(np.float64)
    inst = out.instance.numpy()
    normals = out.normals.numpy().astype(np.float64)
    H, W = depth.shape
    img = background.copy()
    coords = np.zeros((H, W, 3), np.float32)
    light = random_direction(rng)
    light[2] = -abs(light[2]) - 0.3
    light /= np.linalg.norm(light)
    ambient, diffuse = rng.uniform(0.2, 0.7), rng.uniform(0.3, 0.8)
    spec, shine = rng.uniform(0.0, 0.6) * (rng.random() < 0.5), rng.uniform(5.0, 80.0)
    tint = np.clip(1 + rng.normal(scale=0.08, size=3), 0.7, 1.2)
    if headlight:
        default = Light()
        light, tint = default.unit_direction, np.asarray(default.color)
        ambient, diffuse, spec = default.ambient, default.diffuse, 0.0
    Kinv = np.linalg.inv(K)
    for i, (tex, diam) in enumerate(zip(textures, diameters)):
        vv, uu = np.nonzero(inst == i)
        if not len(vv):
            continue
        rays = np.stack([uu, vv, np.ones_like(uu)], axis=1) @ Kinv.T
        cam = rays * depth[vv, uu][:, None]
        R, t = poses[i, :3, :3], poses[i, :3, 3]
        model = (cam - t) @ R / diam
        n_cam = normals[vv, uu]
        albedo = tex(model, n_cam @ R)
        lam = np.clip(n_cam @ light, 0, None)
        view = -rays / np.linalg.norm(rays, axis=1, keepdims=True)
        half = light[None] + view
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        hl = np.clip((n_cam * half).sum(axis=1), 0, None) ** shine
        col = albedo * (ambient + diffuse * lam)[:, None] + spec * hl[:, None]
        img[vv, uu] = np.clip(col * tint, 0, 1)
        if i == 0:
            coords[vv, uu] = model
    return img, coords


def render_pair(
    rng: np.random.Generator,
    mesh: TexturedMesh,
    texture: SolidTexture,
    images: Sequence[np.ndarray],
    *,
    input_size: int = 96,
    max_view_angle: float = 80.0,
    clutter: float = 0.5,
    span: tuple[float, float] = (32.0, 192.0),
    min_matches: int = 32,
    visibility_tolerance: float = 0.02,
    query_style: float = 0.5,
    depth: bool = False,
) -> ViewPair | None:
    """Render one object from two viewpoints, crop both views and match their pixels.

    Args:
        rng: the random generator.
        mesh: the object (centred on its bounding box).
        texture: its solid texture (model points in diameters).
        images: texture images for backgrounds and clutter.
        input_size: side ``S`` of the crops.
        max_view_angle: largest out-of-plane angle between the views, degrees (plus a uniform
            in-plane roll).
        clutter: probability of a second object in each view.
        span: range (log-uniform) of the object's projected diameter before the crop, pixels.
        min_matches: fewer correspondences than this give None.
        visibility_tolerance: depth agreement for a match, fraction of the diameter.
        query_style: probability that view A is rendered as
            :func:`~poseflow.features.lifting.lift_query_features` renders the query (black
            background, the default headlight, no clutter, blur or noise, the object filling
            the crop with the lifting's margin): FunFlow6D matches such renderings against
            observed crops.
        depth: append each view's depth layers to its colour (sensor noise on views not in
            the query's style).

    Returns:
        The :class:`ViewPair`, or None when the views share too few visible pixels.

    Example:
        >>> rng = np.random.default_rng(3)
        >>> imgs = texture_images(rng, count=2, photos=False)
        >>> pair = render_pair(rng, random_mesh(rng), random_texture(rng, imgs), imgs,
        ...                    input_size=32, span=(24.0, 32.0), min_matches=4)
        >>> pair.images.shape, pair.uv_a.shape[1]
        (torch.Size([2, 3, 32, 32]), 2)
    """
    diam = float(np.linalg.norm(mesh.extent()))
    other = random_mesh(rng, diameter=diam * rng.uniform(0.4, 1.0), max_parts=2)
    other_tex = random_texture(rng, images, patchwork=0.0)
    renderer = Renderer([mesh, other], nthreads=1)
    R_a = quaternion_to_rotation(rng.normal(size=4))
    angle = math.radians(rng.uniform(0.0, max_view_angle))
    roll = axis_angle_to_rotation(np.array([0.0, 0.0, rng.uniform(0, 2 * math.pi)]))
    R_b = roll @ axis_angle_to_rotation(random_direction(rng) * angle) @ R_a
    styled = bool(rng.random() < query_style)
    views = [
        _render_view(rng, renderer, R, diam, [texture, other_tex], images,
                     query=styled and k == 0, span=span, input_size=input_size, clutter=clutter,
                     depth=depth)
        for k, R in enumerate((R_a, R_b))
    ]  # fmt: skip
    crops = []
    for k, view in enumerate(views):
        crop = _crop_view(rng, view, query=styled and k == 0, input_size=input_size)
        if crop is None:
            return None
        crops.append(crop)
    pts, uv_b, seen = _matches(crops[0], views[1], crops[1].box, diam, input_size,
                               visibility_tolerance)  # fmt: skip
    if int(seen.sum()) < min_matches:
        return None
    a = crops[0]
    ya, xa = torch.nonzero(a.mask, as_tuple=True)
    # the exact crop position of each lifted point: its rendered pixel, mapped into crop A
    uv_a = pixels_to_crop(a.source[ya, xa][None], a.box, input_size)[0][seen].float()
    return ViewPair(
        images=torch.stack([c.image for c in crops]).float(),
        coords=torch.stack([c.coords for c in crops]).float(),
        mask=torch.stack([c.mask for c in crops]),
        uv_a=uv_a,
        uv_b=uv_b[seen].float(),
        points=pts[seen].float(),
        styled=(styled, False),
    )


@dataclass
class _View:
    """One rendering of the object (and maybe the clutter object).

    The image ``(3, H, W)``, object-0 model points ``(H, W, 3)`` (diameters), the render output,
    the intrinsics ``(3, 3)`` and the object's pose ``(4, 4)``.
    """

    image: torch.Tensor
    coords: np.ndarray
    out: RenderOutput
    K: np.ndarray
    T: np.ndarray


@dataclass
class _Crop:
    """A view's crop of side ``S``.

    The image ``(3, S, S)``, model points ``(S, S, 3)``, the object mask ``(S, S)``, the box
    ``(1, 4)`` and the rendered pixel that each crop pixel shows ``(S, S, 2)``.
    """

    image: torch.Tensor
    coords: torch.Tensor
    mask: torch.Tensor
    box: torch.Tensor
    source: torch.Tensor


def _render_view(
    rng: np.random.Generator,
    renderer: Renderer,
    R: np.ndarray,
    diam: float,
    textures: Sequence[SolidTexture],
    images: Sequence[np.ndarray],
    *,
    query: bool,
    span: tuple[float, float],
    input_size: int,
    clutter: float,
    depth: bool = False,
) -> _View:
    """Render the object turned by ``R``, shaded and degraded (a query view as the lifting).

    With ``depth`` the image gets the depth layers of the object's visible pixels.
    """
    s = math.exp(rng.uniform(math.log(span[0]), math.log(span[1])))
    z = diam * rng.uniform(2.5, 8.0)
    if query:  # lift_query_features: 3 diameters away, the diameter spans the crop / 1.1
        s, z = input_size / 1.1, 3.0 * diam
    f = s * z / diam
    side = math.ceil(1.5 * s) + 8
    c = (side - 1) / 2
    K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [*(rng.uniform(-0.08, 0.08, size=2) * z * (not query)), z]
    T2 = np.eye(4)
    T2[:3, :3] = quaternion_to_rotation(rng.normal(size=4))
    if rng.random() < clutter and not query:
        lateral = random_direction(rng)[:2]
        lateral = lateral / max(np.linalg.norm(lateral), 1e-9)
        dz = rng.uniform(-0.8, 0.8) * diam
        T2[:3, 3] = [*(T[:2, 3] + lateral * rng.uniform(0.45, 0.9) * diam), z + dz]
    else:
        T2[:3, 3] = [0.0, 0.0, -10.0 * z]  # behind the camera: not rendered
    poses = np.stack([T, T2])
    out = renderer.render(poses, K, side, side, rgb=False)
    bg = np.zeros((side, side, 3), np.float32) if query else _background(rng, side, images)
    img, coords = _shade(rng, out, poses, K, textures, [diam, diam], bg, headlight=query)
    x = torch.from_numpy(img).permute(2, 0, 1)
    if not query:
        if rng.random() < 0.5:
            x = _blur(x, float(rng.uniform(0.3, 1.5)))
        noise = torch.from_numpy(rng.normal(size=x.shape).astype(np.float32))
        x = (x + noise * rng.uniform(0.0, 0.03)).clamp(0, 1)
    if depth:
        z = out.depth if query else _SENSOR.apply(out.depth, out.normals, K, rng=rng)
        layers = depth_layers(z[None].float(), (out.instance == 0)[None], torch.tensor([diam]))
        x = torch.cat([x, layers[0]])
    return _View(x, coords, out, K, T)


_SENSOR = DepthNoise()


def _crop_view(
    rng: np.random.Generator, view: _View, *, query: bool, input_size: int
) -> _Crop | None:
    """Crop a view as FunFlow6D crops a target; None when fewer than 16 pixels show it."""
    vis = view.out.instance == 0
    if int(vis.sum()) < 16:
        return None
    vv, uu = torch.nonzero(vis, as_tuple=True)
    cam = (
        torch.stack([uu, vv, torch.ones_like(uu)], 1).double()
        @ torch.from_numpy(np.linalg.inv(view.K)).T
        * view.out.depth[vv, uu, None].double()
    )
    margin = 1.1 if query else rng.uniform(1.0, 1.35)
    box = crop_box_around(cam[None], torch.from_numpy(view.K), margin=margin)
    if not query:
        seed = int(rng.integers(2**31))
        box = jitter_boxes(box, 0.08, generator=torch.Generator().manual_seed(seed))
    S = input_size
    image = crop_resize(view.image[None], box.float(), S)[0]
    grid_v, grid_u = torch.meshgrid(
        torch.arange(vis.shape[0]), torch.arange(vis.shape[1]), indexing="ij"
    )
    planes = [torch.from_numpy(view.coords).permute(2, 0, 1), vis[None].float()]
    layers = torch.cat([*planes, grid_u[None], grid_v[None]]).double()
    m = crop_resize(layers[None], box, S, mode="nearest")[0]
    return _Crop(
        image=image,
        coords=m[:3].permute(1, 2, 0).float().contiguous(),
        mask=m[3] > 0.5,
        box=box,
        source=m[4:].permute(1, 2, 0),  # the rendered pixel each crop pixel shows
    )


def _matches(
    a: _Crop, view_b: _View, box_b: torch.Tensor, diam: float, input_size: int, tolerance: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Object pixels of crop A projected into view B.

    Returns their model points ``(P, 3)`` (diameters), positions in crop B ``(P, 2)`` and
    whether B sees them there ``(P,)``.
    """
    ya, xa = torch.nonzero(a.mask, as_tuple=True)
    pts = a.coords[ya, xa].double()  # (P, 3) in diameters
    out_b, K_b, T_b = view_b.out, view_b.K, view_b.T
    cam_b = (pts * diam) @ torch.from_numpy(T_b[:3, :3]).T + torch.from_numpy(T_b[:3, 3])
    z = cam_b[:, 2]
    uv = (cam_b @ torch.from_numpy(K_b).T)[:, :2] / z[:, None]
    side_b = out_b.depth.shape[0]
    pix = uv.round().long()
    inside = ((pix >= 0) & (pix < side_b)).all(1) & (z > 0)
    pix = pix.clamp(0, side_b - 1)
    d_b = out_b.depth[pix[:, 1], pix[:, 0]].double()
    seen = (
        inside & (out_b.instance[pix[:, 1], pix[:, 0]] == 0) & ((d_b - z).abs() <= tolerance * diam)
    )
    uv_b = pixels_to_crop(uv[None], box_b, input_size)[0]
    seen &= ((uv_b >= -0.5) & (uv_b <= input_size - 0.5)).all(1)
    return pts, uv_b, seen


@dataclass
class PairBatch:
    """A batch of :class:`ViewPair` with a fixed number ``P`` of correspondences each.

    Attributes:
        images_a: crops of view A ``(B, 3, S, S)``.
        images_b: crops of view B ``(B, 3, S, S)``.
        coords_a: model points of crop A's pixels ``(B, S, S, 3)`` (diameters).
        coords_b: the same for crop B ``(B, S, S, 3)``.
        mask_a: object pixels of crop A ``(B, S, S)``.
        mask_b: object pixels of crop B ``(B, S, S)``.
        uv_a: correspondences in crop A ``(B, P, 2)``.
        uv_b: the same in crop B ``(B, P, 2)``.
        points: their model points ``(B, P, 3)`` (diameters).
    """

    images_a: torch.Tensor
    images_b: torch.Tensor
    coords_a: torch.Tensor
    coords_b: torch.Tensor
    mask_a: torch.Tensor
    mask_b: torch.Tensor
    uv_a: torch.Tensor
    uv_b: torch.Tensor
    points: torch.Tensor


def _color_jitter(rng: np.random.Generator, x: torch.Tensor) -> torch.Tensor:
    """Brightness, contrast, saturation, gamma and per-channel gain of ``(3, S, S)``."""
    grey = x.mean(0, keepdim=True)
    x = grey + (x - grey) * rng.uniform(0.6, 1.4)
    x = x.mean() + (x - x.mean()) * rng.uniform(0.7, 1.3)
    gain = torch.from_numpy(rng.uniform(0.9, 1.1, size=(3, 1, 1)).astype(np.float32))
    x = (x * rng.uniform(0.7, 1.3) * gain).clamp(0, 1)
    return x ** float(rng.uniform(0.7, 1.4))


class PairGenerator:
    """Endless training pairs from procedural objects, seeded.

    Each object is rendered as ``pairs_per_object`` pairs (the mesh and texture are the slow
    part to vary); a pool of recent pairs lets a batch reuse some with new colour jitter.

    Args:
        seed: seeds everything.
        input_size: crop side ``S``.
        anchors: correspondences ``P`` per pair in a batch (drawn with replacement when fewer).
        max_view_angle: see :func:`render_pair`.
        clutter: see :func:`render_pair`.
        pool_size: pairs kept for reuse.
        pairs_per_object: pairs rendered per procedural object.
        texture_count: generated print-like texture images.
        photos: add matplotlib's sample photographs to the texture images.
        depth: give each view its depth layers (for a depth-aware descriptor).

    Example:
        >>> gen = PairGenerator(0, input_size=32, anchors=8, texture_count=2, photos=False)
        >>> b = gen.batch(2, fresh=2)
        >>> b.images_a.shape, b.uv_a.shape
        (torch.Size([2, 3, 32, 32]), torch.Size([2, 8, 2]))
    """

    def __init__(
        self,
        seed: int = 0,
        *,
        input_size: int = 96,
        anchors: int = 128,
        max_view_angle: float = 80.0,
        clutter: float = 0.5,
        pool_size: int = 64,
        pairs_per_object: int = 2,
        texture_count: int = 24,
        photos: bool = True,
        depth: bool = False,
    ) -> None:
        self.rng = np.random.default_rng(seed)
        self.input_size = int(input_size)
        self.anchors = int(anchors)
        self.max_view_angle = float(max_view_angle)
        self.clutter = float(clutter)
        self.pool_size = int(pool_size)
        self.pairs_per_object = int(pairs_per_object)
        self.depth = bool(depth)
        self.images = texture_images(self.rng, count=texture_count, photos=photos)
        self.pool: list[ViewPair] = []
        self._object: tuple[TexturedMesh, SolidTexture] | None = None
        self._uses = 0

    def pair(self) -> ViewPair:
        """Render a new pair (retrying views that share too few pixels)."""
        for _ in range(100):
            if self._object is None or self._uses >= self.pairs_per_object:
                self._object = (random_mesh(self.rng), random_texture(self.rng, self.images))
                self._uses = 0
            self._uses += 1
            pair = render_pair(
                self.rng,
                *self._object,
                self.images,
                input_size=self.input_size,
                max_view_angle=self.max_view_angle,
                clutter=self.clutter,
                min_matches=min(32, self.anchors),
                depth=self.depth,
            )
            if pair is not None:
                return pair
            self._object = None
        raise DegenerateInputError("could not render a pair of views with enough overlap")

    def batch(self, batch_size: int, *, fresh: int | None = None) -> PairBatch:
        """A batch: ``fresh`` new pairs (default all) and the rest drawn from the pool.

        Args:
            batch_size: pairs ``B``.
            fresh: new pairs among them (at least 1 while the pool is smaller than the batch).

        Returns:
            The :class:`PairBatch`, colour-jittered per view.
        """
        fresh = batch_size if fresh is None else int(fresh)
        new = [self.pair() for _ in range(max(fresh, batch_size - len(self.pool)))]
        old = [
            self.pool[int(i)]
            for i in self.rng.choice(len(self.pool), size=batch_size - len(new), replace=False)
        ] if batch_size > len(new) else []  # fmt: skip
        self.pool = (self.pool + new)[-self.pool_size :]
        pairs = (new + old)[:batch_size]
        if self.rng.random() < 0.5:  # either view can be the anchor one
            pairs = [_swap(p) for p in pairs]
        idx = [
            torch.from_numpy(self.rng.choice(len(p.uv_a), self.anchors, len(p.uv_a) < self.anchors))
            for p in pairs
        ]
        return PairBatch(
            images_a=torch.stack([self._jitter(p, 0) for p in pairs]),
            images_b=torch.stack([self._jitter(p, 1) for p in pairs]),
            coords_a=torch.stack([p.coords[0] for p in pairs]),
            coords_b=torch.stack([p.coords[1] for p in pairs]),
            mask_a=torch.stack([p.mask[0] for p in pairs]),
            mask_b=torch.stack([p.mask[1] for p in pairs]),
            uv_a=torch.stack([p.uv_a[i] for p, i in zip(pairs, idx)]),
            uv_b=torch.stack([p.uv_b[i] for p, i in zip(pairs, idx)]),
            points=torch.stack([p.points[i] for p, i in zip(pairs, idx)]),
        )

    def _jitter(self, pair: ViewPair, view: int) -> torch.Tensor:
        """A view's crop, its colour jittered unless rendered in the query's style."""
        image = pair.images[view]
        if pair.styled[view]:
            return image
        return torch.cat([_color_jitter(self.rng, image[:3]), image[3:]])


def _swap(p: ViewPair) -> ViewPair:
    return ViewPair(
        p.images.flip(0), p.coords.flip(0), p.mask.flip(0), p.uv_b, p.uv_a, p.points,
        p.styled[::-1],
    )  # fmt: skip
