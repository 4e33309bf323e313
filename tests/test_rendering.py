"""Tests of cmc.mpi.rendering: the fast renderer against its slow twin (outputs and gradients), compositing
known answers, and known-answer renders of textured planes (colour, depth, warp direction, coverage)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import apply_homography, rigid, rotation

from cmc.config import MLPFieldConfig, PyramidFieldConfig
from cmc.errors import ConfigError
from cmc.eval.metrics import psnr
from cmc.geometry.cameras import intrinsics
from cmc.geometry.planes import homographies_ref_from_tgt, pixel_centers, plane_depths, texel_grid
from cmc.mpi._reference import render_rays_reference, render_texture_image_reference
from cmc.mpi.fields import MLPField, PyramidPlaneField, TextureField, ViewColour, flatness
from cmc.mpi.rendering import (
    MPIFrame,
    composite,
    pixel_aligned_margin,
    render_image,
    render_ray_groups,
    render_rays,
    render_texture_image,
)

W, H = 20, 16  # reference image size; with margin 1.5 the plane extent is 30 x 24, offset (5, 4)
MARGIN = 1.5
OFFSET_X, OFFSET_Y = 5, 4


K_REF = intrinsics(20.0, 22.0, W / 2, H / 2)
WORLD_FROM_REF = rigid(rotation([0.3, -1.0, 0.2], 0.8), [0.5, -1.0, 2.0])
NEAR, FAR, D = 2.0, 8.0, 4  # depths 2, 8/3, 4, 8 (uniform in disparity)


def make_frame(dtype: torch.dtype = torch.float32, world_from_ref: np.ndarray = WORLD_FROM_REF) -> MPIFrame:
    frame = MPIFrame.create(K_REF, world_from_ref, NEAR, FAR, D, W, H, MARGIN)
    if dtype == torch.float32:
        return frame
    return MPIFrame(
        frame.K.to(dtype),
        frame.world_from_ref.to(dtype),
        torch.as_tensor(plane_depths(NEAR, FAR, D), dtype=dtype),
        W,
        H,
        frame.margin,
    )


def target_cameras() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Target (K, world_from_tgt) pairs, relative to the reference camera."""
    return {
        "reference": (K_REF, WORLD_FROM_REF),
        "moved": (
            intrinsics(24.0, 23.0, 11.0, 7.5),
            WORLD_FROM_REF @ rigid(rotation([1, 2, 0.5], 0.08), [0.4, -0.2, 0.3]),
        ),
        # Turned and moved so far that about 30 % of its image looks past the planes' extent.
        "turned": (
            intrinsics(24.0, 23.0, 11.0, 7.5),
            WORLD_FROM_REF @ rigid(rotation([0.2, 1, 0], 0.4), [1.5, 0.2, 0.3]),
        ),
        # Inside the MPI: planes 0 and 1 (z = 2, 2.67) are behind it.
        "between_planes": (K_REF, WORLD_FROM_REF @ rigid(np.eye(3), [0.1, 0.1, 3.0])),
    }


def random_pyramid(seed: int, dtype: torch.dtype) -> PyramidPlaneField:
    torch.manual_seed(seed)
    h, w = round(H * MARGIN), round(W * MARGIN)
    cfg = PyramidFieldConfig(base_groups=1, base_interpolation="bilinear")
    field = PyramidPlaneField(D, h, w, cfg, torch.rand(3, h, w))
    with torch.no_grad():
        for p in field.parameters():
            p.add_(0.7 * torch.randn_like(p))
    return field.to(dtype)


def random_mlp(seed: int, dtype: torch.dtype) -> MLPField:
    torch.manual_seed(seed)
    return MLPField(D, MLPFieldConfig(width=16, depth=2, pe_freqs=3)).to(dtype)


def target_uv(dtype: torch.dtype) -> torch.Tensor:
    """Every pixel centre of a W x H target plus random off-centre points, many far outside the image."""
    g = torch.Generator().manual_seed(0)
    size = torch.tensor([float(W), float(H)])
    extra = (3 * torch.rand(60, 2, generator=g) - 1) * size
    return torch.cat([pixel_centers(W, H), extra]).to(dtype)


# --- fast renderer vs slow twin ------------------------------------------------------------------


@pytest.mark.parametrize("target", list(target_cameras()))
@pytest.mark.parametrize("kind", ["pyramid", "mlp"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_render_rays_matches_reference(target: str, kind: str, dtype: torch.dtype) -> None:
    frame = make_frame(dtype)
    field = (random_pyramid if kind == "pyramid" else random_mlp)(1, dtype)
    K_t, P_t = (torch.as_tensor(a, dtype=dtype) for a in target_cameras()[target])
    uv = target_uv(dtype)
    params = list(field.parameters())
    g = torch.Generator().manual_seed(2)
    wr, wd, wa = (torch.randn(*s, generator=g, dtype=dtype) for s in ((len(uv), 3), (len(uv),), (len(uv),)))

    def run(fn):
        out = fn(field, frame, K_t, P_t, uv)
        loss = (out.rgb * wr).sum() + (out.depth * wd).sum() + (out.acc * wa).sum()
        return out, torch.autograd.grad(loss, params, allow_unused=True)

    fast, grads_fast = run(render_rays)
    slow, grads_slow = run(render_rays_reference)
    assert fast.rgb.shape == (len(uv), 3) and fast.depth.shape == (len(uv),) and fast.acc.shape == (len(uv),)
    tol = {"rtol": 0, "atol": 1e-9} if dtype == torch.float64 else {"rtol": 1e-4, "atol": 1e-4}
    torch.testing.assert_close(fast.rgb, slow.rgb, **tol)
    torch.testing.assert_close(fast.acc, slow.acc, **tol)
    torch.testing.assert_close(fast.depth, slow.depth, rtol=tol["rtol"], atol=tol["atol"] * FAR)
    # The comparison is not vacuous: some rays hit all the planes and some miss some of them.
    assert (fast.acc > 0.99).sum() > 50
    assert (fast.acc < 0.99).sum() > 10
    for name, a, b in zip([n for n, _ in field.named_parameters()], grads_fast, grads_slow, strict=True):
        assert a is not None and b is not None, name
        message = lambda m, n=name: f"{n}: {m}"  # noqa: E731
        torch.testing.assert_close(a, b, rtol=tol["rtol"], atol=tol["atol"] * 10, msg=message)
    assert sum(float(a.abs().sum()) for a in grads_fast) > 0


# --- whole-image render of fixed textures vs its slow twin ----------------------------------------


def random_premultiplied(num_planes: int, h: int, w: int, seed: int, dtype: torch.dtype) -> torch.Tensor:
    """[D, 4, h, w] premultiplied RGBA with baked-MPI-like alpha: mostly faint, some opaque texels,
    transparent 8x8 blocks, and an opaque back plane."""
    g = torch.Generator().manual_seed(seed)
    alpha = torch.rand(num_planes, 1, h, w, generator=g, dtype=dtype) ** 4
    blocks = (torch.rand(num_planes, 1, -(-h // 8), -(-w // 8), generator=g, dtype=dtype) > 0.3).to(dtype)
    alpha = alpha * blocks.repeat_interleave(8, 2).repeat_interleave(8, 3)[:, :, :h, :w]
    alpha[-1] = 1.0
    return torch.cat([torch.rand(num_planes, 3, h, w, generator=g, dtype=dtype) * alpha, alpha], 1)


def texture_targets() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """target_cameras() plus two inside the MPI looking back, which see planes 0 and 1 from
    behind and nothing else; the second has its centre exactly on plane 2 (z = 4), edge-on."""
    turn = rotation([0, 1, 0], math.pi)
    return {
        **target_cameras(),
        "inside_looking_back": (K_REF, WORLD_FROM_REF @ rigid(turn, [0.1, 0.1, 3.0])),
        "on_plane_looking_back": (K_REF, rigid(turn, [1.0, 1.0, 4.0])),  # with an identity reference pose
    }


@pytest.mark.parametrize("target", list(texture_targets()))
@pytest.mark.parametrize("blocks", [1, 3])  # 3 pixel batches: the last one padded
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_render_texture_image_matches_reference(target: str, blocks: int, dtype: torch.dtype) -> None:
    frame = make_frame(dtype, world_from_ref=np.eye(4) if target == "on_plane_looking_back" else WORLD_FROM_REF)
    rgba = random_premultiplied(D, round(H * MARGIN), round(W * MARGIN), 8, dtype)
    K_t, P_t = (torch.as_tensor(a, dtype=dtype) for a in texture_targets()[target])
    fast = render_texture_image(rgba, frame, K_t, P_t, W, H, blocks=blocks)
    slow = render_texture_image_reference(rgba, frame, K_t, P_t, W, H)
    assert fast.rgb.shape == (W * H, 3) and fast.depth.shape == (W * H,) and fast.acc.shape == (W * H,)
    tol = {"rtol": 0, "atol": 1e-9} if dtype == torch.float64 else {"rtol": 1e-4, "atol": 1e-5}
    torch.testing.assert_close(fast.rgb, slow.rgb, **tol)
    torch.testing.assert_close(fast.acc, slow.acc, **tol)
    torch.testing.assert_close(fast.depth, slow.depth, rtol=tol["rtol"], atol=tol["atol"] * FAR)
    assert float(slow.acc.max()) > 0.5  # not vacuous
    if target == "turned":
        assert float(slow.acc.min()) < 0.5  # some pixels look past the planes' extent


@pytest.mark.parametrize("target", ["reference", "moved", "between_planes"])
def test_render_texture_image_matches_ray_reference(target: str) -> None:
    """The whole-image path of fixed textures agrees with the ray twin, render_rays_reference
    over the same TextureField, where the two must agree: with alpha constant on each plane
    (then interpolating premultiplied or straight colour is the same) at pixels whose plane
    crossings all lie inside the planes' extent, away from its one-texel border."""
    frame, dtype = make_frame(torch.float64), torch.float64
    h, w = round(H * MARGIN), round(W * MARGIN)
    g = torch.Generator().manual_seed(11)
    alpha = torch.rand(D, 1, 1, 1, generator=g, dtype=dtype).expand(D, 1, h, w)
    field = TextureField(torch.cat([torch.rand(D, 3, h, w, generator=g, dtype=dtype), alpha], 1))
    K_t, P_t = (torch.as_tensor(a, dtype=dtype) for a in target_cameras()[target])
    fast = render_texture_image(field.premultiplied, frame, K_t, P_t, W, H)
    uv = pixel_centers(W, H).to(dtype)
    slow = render_rays_reference(field, frame, K_t, P_t, uv)
    H_ref_from_tgt = homographies_ref_from_tgt(frame.K, frame.ref_from_world, K_t, P_t, frame.depths)
    uv_ref, in_front = apply_homography(H_ref_from_tgt, uv)  # [P, D, 2], [P, D]
    grid = frame.grid_from_pixels(uv_ref)
    inner = (grid.abs() <= 1 - 2 / torch.tensor([w, h], dtype=dtype)).all(-1)
    keep = (inner | ~in_front).all(-1)  # planes behind the camera are transparent in both
    assert float(keep.double().mean()) > 0.6
    tol = {"rtol": 0, "atol": 1e-9}
    torch.testing.assert_close(fast.rgb[keep], slow.rgb[keep], **tol)
    torch.testing.assert_close(fast.acc[keep], slow.acc[keep], **tol)
    torch.testing.assert_close(fast.depth[keep], slow.depth[keep], rtol=0, atol=1e-9 * FAR)


@pytest.mark.parametrize("size", [(504, 378), (21, 15), (97, 64)])
def test_the_reference_view_reads_texel_centres(size) -> None:
    """The plane extent adds whole pixels on each side (:func:`pixel_aligned_margin`), so each
    pixel centre of the reference view is a texel centre: rendered at its own camera, an MPI
    gives back its textures' texels exactly, with no resampling between texels (which would
    low-pass the photo's finest detail)."""
    width, height = size
    K = intrinsics(0.8 * width, 0.8 * width, width / 2, height / 2)
    frame = MPIFrame.create(K, np.eye(4), 1.5, 9.0, 3, width, height, 1.2)
    h, w = frame.extent
    px, py = (w - width) // 2, (h - height) // 2
    assert frame.margin == pixel_aligned_margin(width, height, 1.2) and abs(frame.margin[0] - 1.2) <= 1 / width
    assert (w - width, h - height) == (2 * px, 2 * py)
    g = frame.grid_from_pixels(pixel_centers(width, height))
    texel = (g + 1) / 2 * g.new_tensor([w, h]) - 0.5
    torch.testing.assert_close(texel, texel.round(), rtol=0, atol=1e-3)
    rgba = random_premultiplied(3, h, w, 4, torch.float32)
    out = render_texture_image(rgba, frame, frame.K, frame.world_from_ref, width, height)
    crop = rgba[:, :, py : py + height, px : px + width]
    trans = torch.cumprod(torch.cat([torch.ones_like(crop[:1, 3]), 1 - crop[:-1, 3]]), 0)
    expected = (crop[:, :3] * trans[:, None]).sum(0)  # premultiplied, front to back
    torch.testing.assert_close(out.rgb.reshape(height, width, 3), expected.permute(1, 2, 0), rtol=0, atol=5e-4)


def test_render_texture_image_matches_reference_at_real_size() -> None:
    """A baked fern-sized MPI (504 x 378 image, 48 planes, margin 1.2, f = 407 px, depths 1.2 to
    25): the fast path agrees with its twin within the baked renderer's accuracy bound (colour
    PSNR >= 50 dB, depth max relative error <= 1e-3 where covered). Measured: about 100 dB and
    at most 5e-4, float32 rounding (each is within 5e-4 of the twin run in float64)."""
    width, height, planes, margin = 504, 378, 48, 1.2
    K = intrinsics(407.0, 407.0, width / 2, height / 2)
    frame = MPIFrame.create(K, np.eye(4), 1.2, 25.0, planes, width, height, margin)
    rgba = random_premultiplied(planes, *frame.extent, 9, torch.float32)
    targets = [
        rigid(rotation([0.1, 1, 0.05], 0.05), [0.2, -0.05, 0.1]),  # a nearby input-like view
        rigid(rotation([0.3, -1, 0.6], 0.12), [-0.5, 0.2, -0.3]),  # rolled and turned: partly uncovered
        rigid(rotation([0, 0, 1], 0.03), [0.05, 0.02, 1.5]),  # moved in past the nearest planes
    ]
    for world_from_tgt in targets:
        P_t = torch.as_tensor(world_from_tgt, dtype=torch.float32)
        K_t = torch.as_tensor(K, dtype=torch.float32)
        fast = render_texture_image(rgba, frame, K_t, P_t, width, height)
        slow = render_texture_image_reference(rgba, frame, K_t, P_t, width, height)
        covered = slow.acc > 1e-3
        assert float(covered.float().mean()) > 0.5
        assert psnr(fast.rgb.reshape(height, width, 3).numpy(), slow.rgb.reshape(height, width, 3).numpy()) >= 50
        # Depth as render_image reports it (blend divides by coverage): float32 rounding of the
        # grid coordinates moves the raw depth of faintly covered edge pixels by up to 1 % in
        # every implementation, the slow twin included, but not the depth per unit coverage.
        depth_fast, depth_slow = (o.depth[covered] / o.acc[covered] for o in (fast, slow))
        assert float(((depth_fast - depth_slow).abs() / depth_slow).max()) <= 1e-3
        # Coverage: at a faintly covered edge pixel each float32 path lies up to 1e-4 from the
        # float64 render, the two up to twice that apart.
        torch.testing.assert_close(fast.acc, slow.acc, rtol=0, atol=2e-4)


# --- compositing known answers -------------------------------------------------------------------


def test_composite_single_opaque_plane() -> None:
    g = torch.Generator().manual_seed(3)
    rgb = torch.rand(6, 5, 3, generator=g)
    depth = torch.linspace(1.0, 5.0, 5).expand(6, 5)
    for k in range(5):
        alpha = torch.zeros(6, 5)
        alpha[:, k] = 1.0
        alpha[:, k + 1 :] = torch.rand(6, 4 - k, generator=g)  # hidden behind plane k
        out = composite(rgb, alpha, depth)
        torch.testing.assert_close(out.rgb, rgb[:, k])
        torch.testing.assert_close(out.depth, depth[:, k])
        torch.testing.assert_close(out.acc, torch.ones(6))


def test_composite_half_alpha() -> None:
    rgb = torch.eye(3)[None]  # plane k is pure colour k
    alpha = torch.tensor([[0.5, 0.5, 1.0]])
    depth = torch.tensor([[2.0, 3.0, 6.0]])
    out = composite(rgb, alpha, depth)
    torch.testing.assert_close(out.rgb, torch.tensor([[0.5, 0.25, 0.25]]))
    torch.testing.assert_close(out.depth, torch.tensor([0.5 * 2 + 0.25 * 3 + 0.25 * 6]))
    torch.testing.assert_close(out.acc, torch.tensor([1.0]))
    # Without the opaque back plane a quarter of the light passes through.
    out = composite(rgb[:, :2], alpha[:, :2], depth[:, :2])
    torch.testing.assert_close(out.rgb, torch.tensor([[0.5, 0.25, 0.0]]))
    torch.testing.assert_close(out.acc, torch.tensor([0.75]))


def test_composite_accumulation_identity() -> None:
    g = torch.Generator().manual_seed(4)
    alpha = torch.rand(10, 7, generator=g)
    out = composite(torch.ones(10, 7, 3), alpha, torch.ones(10, 7))
    expected = 1 - torch.prod(1 - alpha, dim=1)
    torch.testing.assert_close(out.acc, expected)
    torch.testing.assert_close(out.rgb, expected[:, None].expand(10, 3))  # white planes
    torch.testing.assert_close(out.depth, expected)  # unit depth
    empty = composite(torch.rand(2, 3, 3, generator=g), torch.zeros(2, 3), torch.ones(2, 3))
    assert float(empty.acc.abs().max()) == 0 and float(empty.rgb.abs().max()) == 0


# --- known-answer renders ---------------------------------------------------------------------------


def texture(planes: dict[int, tuple[tuple[int, int, int, int], tuple[float, float, float]]]) -> torch.Tensor:
    """[D, 4, 24, 30] RGBA: plane k opaque with colour c in plane-extent rows r0:r1, cols c0:c1; the
    back plane is grey (and always opaque)."""
    rgba = torch.zeros(D, 4, round(H * MARGIN), round(W * MARGIN))
    rgba[D - 1, :3] = 0.5
    for k, ((r0, r1, c0, c1), colour) in planes.items():
        rgba[k, :3, r0:r1, c0:c1] = torch.tensor(colour)[:, None, None]
        rgba[k, 3, r0:r1, c0:c1] = 1.0
    return rgba


def test_render_at_reference_camera_textured_rectangles() -> None:
    """At the reference camera, image pixel (i, j) sees texel (i + 4, j + 5) of every plane."""
    depths = plane_depths(NEAR, FAR, D)
    # Plane 2: red rectangle over image rows 3..9, cols 4..12; plane 1: blue one over rows 7..11,
    # cols 10..15, in front of it where they overlap.
    red, blue = (0.9, 0.2, 0.1), (0.1, 0.2, 0.8)
    tex = texture({2: ((3 + 4, 10 + 4, 4 + 5, 13 + 5), red), 1: ((7 + 4, 12 + 4, 10 + 5, 16 + 5), blue)})
    out = render_image([TextureField(tex)], [make_frame()], K_REF, WORLD_FROM_REF, W, H)
    assert out.rgb.shape == (H, W, 3) and out.depth.shape == (H, W) and out.acc.shape == (H, W)
    exp_depth = np.full((H, W), depths[3])
    exp_rgb = np.full((H, W, 3), 0.5)
    exp_depth[3:10, 4:13], exp_rgb[3:10, 4:13] = depths[2], red
    exp_depth[7:12, 10:16], exp_rgb[7:12, 10:16] = depths[1], blue
    np.testing.assert_allclose(out.acc.numpy(), 1.0, atol=1e-5)
    np.testing.assert_allclose(out.depth.numpy(), exp_depth, atol=1e-3)
    np.testing.assert_allclose(out.rgb.numpy(), exp_rgb, atol=1e-4)


@pytest.mark.parametrize(("k", "shift"), [(2, 4), (3, 2)])
def test_sideways_target_shifts_by_disparity(k: int, shift: int) -> None:
    """Moving the camera right by tx moves content at depth z left by fx * tx / z pixels.

    fx = 20, tx = 0.8: 4 px for plane 2 (z = 4), 2 px for plane 3 (z = 8).
    """
    depths = plane_depths(NEAR, FAR, D)
    assert depths[k] == pytest.approx(20.0 * 0.8 / shift)
    rgba = torch.zeros(D, 4, round(H * MARGIN), round(W * MARGIN))
    rgba[k] = torch.rand(4, *rgba.shape[2:], generator=torch.Generator().manual_seed(k))
    rgba[k, 3] = 1.0
    frame = make_frame()
    world_from_tgt = WORLD_FROM_REF @ rigid(np.eye(3), [0.8, 0.0, 0.0])
    K = intrinsics(20.0, 22.0, W / 2, H / 2)
    out = render_image([TextureField(rgba)], [frame], K, world_from_tgt, W, H)
    # Target pixel (i, j) sees reference pixel (i, j + shift), i.e. texel (i + 4, j + shift + 5).
    expected = rgba[k, :3, OFFSET_Y : OFFSET_Y + H, OFFSET_X + shift : OFFSET_X + shift + W].permute(1, 2, 0)
    torch.testing.assert_close(out.rgb, expected, rtol=0, atol=1e-4)
    torch.testing.assert_close(out.depth, torch.full((H, W), float(depths[k])), rtol=0, atol=1e-4)
    torch.testing.assert_close(out.acc, torch.ones(H, W), rtol=0, atol=1e-5)
    # The same with an explicit stripe: reference column 12 appears at target column 12 - shift.
    stripe = torch.zeros(D, 4, *rgba.shape[2:])
    stripe[k, :, :, OFFSET_X + 12] = 1.0
    out = render_image([TextureField(stripe)], [frame], K, world_from_tgt, W, H)
    cols = torch.nonzero(out.rgb[H // 2, :, 0] > 0.5).flatten().tolist()
    assert cols == [12 - shift]


def test_forward_target_depth_is_target_z() -> None:
    """Moving the camera 1 unit forward: the plane at z = 4 is at target depth 3, and it looks bigger."""
    rgba = torch.zeros(D, 4, round(H * MARGIN), round(W * MARGIN))
    rgba[2, 3] = 1.0
    rgba[2, 0, :, OFFSET_X + 14] = 1.0  # a red column 4 px right of the centre (u = 14.5 vs cx = 10)
    world_from_tgt = WORLD_FROM_REF @ rigid(np.eye(3), [0.0, 0.0, 1.0])
    out = render_image([TextureField(rgba)], [make_frame()], K_REF, world_from_tgt, W, H)
    torch.testing.assert_close(out.depth, torch.full((H, W), 3.0), rtol=0, atol=1e-4)
    # u_ref - cx = 4.5 at z = 4 becomes 4.5 * 4 / 3 = 6 at z = 3: target u = 16, between columns 15 and 16.
    row = out.rgb[H // 2, :, 0]
    torch.testing.assert_close(row[15], row[16])
    assert float(row[15]) > 0.3 and float(row[[13, 18]].max()) < 1e-4


# --- render_image: MPI selection, blending, coverage -----------------------------------------------


def test_render_image_mpi_index_and_identical_blend() -> None:
    fa, fb = random_pyramid(5, torch.float32), random_pyramid(6, torch.float32)
    frame_a = make_frame()
    frame_b = make_frame(world_from_ref=WORLD_FROM_REF @ rigid(rotation([0, 1, 0], 0.1), [0.7, 0.0, 0.0]))
    K, pose = target_cameras()["turned"]
    single_a = render_image([fa], [frame_a], K, pose, W, H)
    single_b = render_image([fb], [frame_b], K, pose, W, H)
    assert float(single_a.acc.min()) < 0.5 < float(single_a.acc.max())  # partial coverage: a real check
    for index, single in ((0, single_a), (1, single_b)):
        picked = render_image([fa, fb], [frame_a, frame_b], K, pose, W, H, mpi_index=index)
        for name in ("rgb", "depth", "acc"):
            torch.testing.assert_close(getattr(picked, name), getattr(single, name), rtol=0, atol=1e-6)
    # The two MPIs differ, so blending them differs from either one.
    both = render_image([fa, fb], [frame_a, frame_b], K, pose, W, H)
    assert float((both.rgb - single_a.rgb).abs().max()) > 1e-2
    # Two identical MPIs blend into the same image as one of them.
    twice = render_image([fa, fa], [frame_a, frame_a], K, pose, W, H, chunk=37)
    for name in ("rgb", "depth", "acc"):
        torch.testing.assert_close(getattr(twice, name), getattr(single_a, name), rtol=0, atol=1e-5)


def test_render_image_identical_blend_at_reference_camera() -> None:
    field, frame = random_pyramid(5, torch.float32), make_frame()
    single = render_image([field], [frame], K_REF, WORLD_FROM_REF, W, H)
    twice = render_image([field, field], [frame, frame], K_REF, WORLD_FROM_REF, W, H)
    torch.testing.assert_close(twice.rgb, single.rgb, rtol=0, atol=1e-5)


def test_render_image_coverage_zero_outside_planes() -> None:
    """A target at the reference camera with a 3x wider image: only the plane extent is covered,
    both through the whole-image path of fixed textures and the ray path of a pyramid field."""
    tex = texture({})
    K = intrinsics(20.0, 22.0, W / 2 + W, H / 2)  # target column j looks at reference u = j + 0.5 - 20
    inside = torch.zeros(H, 3 * W, dtype=torch.bool)
    inside[:, W - OFFSET_X : 2 * W + OFFSET_X] = True  # reference u in [-5, 25]: the extent
    out = render_image([TextureField(tex)], [make_frame()], K, WORLD_FROM_REF, 3 * W, H)
    torch.testing.assert_close(out.acc, inside.float(), rtol=0, atol=1e-5)
    assert float(out.rgb[~inside].abs().max()) < 1e-5 and float(out.depth[~inside].abs().max()) < 1e-5
    torch.testing.assert_close(out.rgb[inside], torch.full((int(inside.sum()), 3), 0.5), rtol=0, atol=1e-5)
    hard = render_image([random_pyramid(3, torch.float32)], [make_frame()], K, WORLD_FROM_REF, 3 * W, H)
    torch.testing.assert_close(hard.acc, inside.float(), rtol=0, atol=1e-5)
    # Looking backwards from the reference camera nothing is in front: no coverage at all.
    back = WORLD_FROM_REF @ rigid(rotation([0, 1, 0], math.pi), [0, 0, 0])
    out = render_image([TextureField(tex)], [make_frame()], K_REF, back, W, H)
    assert float(out.acc.abs().max()) == 0 and float(out.rgb.abs().max()) == 0


def test_faint_samples_read_grey_and_move_their_ray_by_at_most_half_their_weight() -> None:
    """render_ray_groups with colour_grad_min_weight: the pyramid field samples no colour for
    the samples weighing less (they read 0.5), so each ray's colour moves by at most half their
    summed weight; its depth, coverage and weights stay as they were."""
    field, frame = random_pyramid(8, torch.float32), make_frame()
    K, pose = target_cameras()["moved"]
    K_t, pose_t = torch.as_tensor(K, dtype=torch.float32), torch.as_tensor(pose, dtype=torch.float32)
    args = (K_t, pose_t, target_uv(torch.float32))
    with torch.no_grad():
        (full,) = render_ray_groups(field, frame, [args])
        (cut,) = render_ray_groups(field, frame, [args], colour_grad_min_weight=0.2)
    faint = full.weights < 0.2
    assert 0.1 < float(faint[full.acc > 0].float().mean()) < 0.9
    for a, b in ((full.depth, cut.depth), (full.acc, cut.acc), (full.weights, cut.weights)):
        assert torch.equal(a, b)
    moved = (cut.rgb - full.rgb).abs().amax(-1)
    bound = 0.5 * (full.weights * faint).sum(-1)
    assert bool((moved <= bound + 1e-6).all()) and float(moved.max()) > 1e-3


def test_color_grad_scales_the_gradients_to_colour_only() -> None:
    """render_ray_groups(color_grad=[f]): the composite does not depend on f; the gradients of the
    field's colours are f times those at f = 1 (False: none),
    the alpha gradients unchanged (LossConfig.cross_view_colour)."""
    field, frame = random_pyramid(7, torch.float32), make_frame()
    K, pose = target_cameras()["moved"]
    uv = target_uv(torch.float32)
    args = (torch.as_tensor(K, dtype=torch.float32), torch.as_tensor(pose, dtype=torch.float32), uv)
    grads = {}
    for flag in (True, 0.25, False):
        field.zero_grad()
        (out,) = render_ray_groups(field, frame, [args], color_grad=[flag])
        out.rgb.sum().backward()
        grad = lambda p: torch.zeros_like(p) if p.grad is None else p.grad.clone()  # noqa: E731
        grads[flag] = (out.rgb.detach(), grad(field.colour_levels[0]), grad(field.base), grad(field.alpha_levels[0]))
    rgb1, colour1, base1, alpha1 = grads[True]
    assert float(colour1.abs().sum()) > 0 and float(base1.abs().sum()) > 0 and float(alpha1.abs().sum()) > 0
    for flag, f in ((0.25, 0.25), (False, 0.0)):
        rgb, colour, base, alpha = grads[flag]
        torch.testing.assert_close(rgb, rgb1)
        torch.testing.assert_close(colour, f * colour1)
        torch.testing.assert_close(base, f * base1)
        torch.testing.assert_close(alpha, alpha1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_groups_render_as_alone_and_one_without_colour_gradient_samples_no_colour(dtype) -> None:
    """render_ray_groups with two cameras in one query renders each as it does alone; with
    colour_grad_min_weight, a group whose colour factor is 0 (the unseen poses' without L_ac)
    has no colour sampled (0.5 on every plane) and its depth, coverage and weights unchanged.
    float32: the compiled kernels; float64: their torch twins (the GPU's path)."""
    field, frame = random_pyramid(8, dtype), make_frame(dtype)
    cams = target_cameras()
    groups = [
        (torch.as_tensor(K, dtype=dtype), torch.as_tensor(P, dtype=dtype), target_uv(dtype))
        for K, P in (cams["moved"], cams["reference"])
    ]
    with torch.no_grad():
        alone = [render_ray_groups(field, frame, [g])[0] for g in groups]
        together = render_ray_groups(field, frame, groups)
        cut = render_ray_groups(field, frame, groups, color_grad=[1.0, 0.0], colour_grad_min_weight=1e-3)
    for a, b in zip(alone, together, strict=True):
        for x, y in ((a.rgb, b.rgb), (a.depth, b.depth), (a.acc, b.acc), (a.weights, b.weights)):
            torch.testing.assert_close(x, y, rtol=0, atol=1e-6)
    torch.testing.assert_close(cut[1].rgb, 0.5 * together[1].acc[:, None].expand(-1, 3), rtol=0, atol=1e-6)
    assert float((cut[1].rgb - together[1].rgb).abs().max()) > 0.05
    for a, b in ((together[1].depth, cut[1].depth), (together[1].acc, cut[1].acc)):
        assert torch.equal(a, b)
    moved = (cut[0].rgb - together[0].rgb).abs().amax(-1)
    assert bool((moved <= 0.5 * (together[0].weights * (together[0].weights < 1e-3)).sum(-1) + 1e-6).all())


@pytest.mark.parametrize("num_planes", [8, 7])
def test_pyramid_base_groups_give_plane_k_the_base_k_times_g_over_d(num_planes):
    """With ``base_groups`` G, plane k's colour uses base k * G // D (also when G does not divide
    D); all bases start as the reference photo, so the field starts as with one base."""
    torch.manual_seed(0)
    D, h, w = num_planes, 12, 16
    rgb, alpha = torch.rand(3, h, w), torch.rand(D, 6, 8)
    one = PyramidPlaneField(D, h, w, PyramidFieldConfig(base_groups=1), rgb, alpha)
    three = PyramidPlaneField(D, h, w, PyramidFieldConfig(base_groups=3), rgb, alpha)
    g, z, dirs = torch.rand(40, D, 2) * 2 - 1, torch.linspace(-1, 1, D), torch.zeros(40, 3)
    with torch.no_grad():
        assert torch.equal(one(g, z, dirs)[0], three(g, z, dirs)[0])
        three.base[1] += 4.0
        changed = (three(g, z, dirs)[0] - one(g, z, dirs)[0]).abs().amax((0, 2)) > 0.01
    assert changed.tolist() == [k * 3 // D == 1 for k in range(D)]
    with pytest.raises(ConfigError):
        PyramidPlaneField(2, h, w, PyramidFieldConfig(base_groups=3), rgb, alpha[:2])


def test_a_model_with_fewer_planes_than_the_presets_base_groups_gets_one_base_per_plane():
    """``fast`` has 8 base colour groups; a model set to 4 planes by hand builds with one base per
    plane instead of refusing a setting the user did not make, and renders its input view."""
    from dataclasses import replace

    from cmc.config import preset_config
    from cmc.data.datasets import synthetic_scene
    from cmc.method.model import CMCModel

    cfg = preset_config("fast").model
    assert cfg.pyramid.base_groups == 8
    scene = synthetic_scene(num_views=3, width=32, height=24)
    model = CMCModel(scene, replace(cfg, num_planes=4))
    assert model.cfg.pyramid.base_groups == 4
    assert [f.base.shape[0] for f in model.fields] == [4, 4, 4]
    with torch.no_grad():
        out = model.render(scene.cameras.K[0], scene.cameras.world_from_cam[0], 32, 24)
    assert psnr(out.rgb, scene.images[0]) > 20  # untrained: each base starts as the photo


# --- the view-dependent colour term of training (ViewColour) ---------------------------------------


def _view_colour(dtype: torch.dtype, slope_scale: float = 0.1, groups: int = 2) -> tuple[MPIFrame, ViewColour]:
    """The test frame and a ViewColour on it over a flat grey photo (its mask 1 everywhere)."""
    frame = make_frame(dtype)
    photo = torch.full((3, *frame.extent), 0.5, dtype=dtype)
    return frame, ViewColour(groups, (6, 8), frame.grid_from_camera(dtype), slope_scale, photo).to(dtype)


def test_view_colour_is_zero_for_the_reference_camera_and_follows_a_sideways_cameras_parallax() -> None:
    """A point X on plane k (reference frame) seen from a camera moved by b along x: the ray's
    slope differs from the reference ray's by (-b / z_k, 0); the term is the texture's x
    coefficient times that over ``slope_scale``, per channel, and 0 from the reference camera."""
    frame, vc = _view_colour(torch.float64, slope_scale=0.1, groups=1)
    with torch.no_grad():
        vc.texture.zero_()
        vc.texture[0, 0] = 2.0  # red's x coefficient
        vc.texture[0, 3] = -1.0  # green's y coefficient
    z = frame.depths  # [D]
    g = torch.Generator().manual_seed(0)
    xy_over_z = (torch.rand(10, 2, generator=g, dtype=torch.float64) - 0.5) * 0.6  # well inside the extent
    X = torch.cat([xy_over_z[None] * z[:, None, None], z[:, None, None].expand(-1, 10, 1)], -1)  # [D, R, 3]
    M = frame.grid_from_camera(torch.float64)
    grid = torch.einsum("ij,dri->drj", M.T, X / X[..., 2:3]).contiguous()  # [D, R, 2]
    bounds = [0, D]
    for b in (0.0, 0.3):
        # The rays through plane k's points from the camera at (b, 0, 0), one plane at a time.
        logits = []
        for k in range(D):
            d = X[k] - torch.tensor([b, 0.0, 0.0], dtype=torch.float64)
            plane_k = grid[k : k + 1].expand(D, -1, -1).contiguous()
            with torch.no_grad():
                out = vc.logits(plane_k, d / d.norm(dim=-1, keepdim=True), bounds, None)
            logits.append(out[k])  # [3, R]
        logits = torch.stack(logits)  # [D, 3, R]
        expected_x = (-b / z / 0.1).clamp(-2, 2)[:, None].expand(-1, 10)
        torch.testing.assert_close(logits[:, 0], 2.0 * expected_x)
        torch.testing.assert_close(logits[:, 1], torch.zeros_like(expected_x))  # green's y: no vertical parallax
        torch.testing.assert_close(logits[:, 2], torch.zeros_like(expected_x))
    assert float(logits[:, 0].abs().min()) > 0.1  # the moved camera's term is not vacuous
    no_direction = torch.zeros(10, 3, dtype=torch.float64)
    with torch.no_grad():  # the zero vector (no direction): the reference camera's colours
        assert torch.equal(vc.logits(grid, no_direction, bounds, None), torch.zeros(D, 3, 10, dtype=torch.float64))


def test_view_colour_compiled_matches_grid_sample_in_values_and_gradients() -> None:
    """The CPU's fused pass (float32) against the torch formula with ``grid_sample`` (float64),
    with a ``where``, a photo textured on its right (mask 0 there: samples skipped), the
    reference camera's own rays (delta 0) and rays that do not point into the planes."""
    g = torch.Generator().manual_seed(1)
    frame = make_frame(torch.float64)
    h, w = frame.extent
    photo = torch.full((3, h, w), 0.5, dtype=torch.float64)
    photo[:, :, w // 2 :] = torch.rand(3, h, w - w // 2, generator=g, dtype=torch.float64)
    grid = torch.rand(D, 60, 2, generator=g, dtype=torch.float64) * 2.2 - 1.1
    dirs = torch.randn(60, 3, generator=g, dtype=torch.float64) * 0.2
    dirs[:, 2] += 1
    dirs[50:55, 2] = -dirs[50:55, 2]  # away from the planes
    M = frame.grid_from_camera(torch.float64)
    dirs[55:] = torch.cat([(grid[0, 55:] - M[:, 2]) / M.diagonal()[:2], torch.ones(5, 1, dtype=torch.float64)], 1)
    grid[:, 55:] = grid[0, 55:]  # the reference camera's rays: the same point on every plane
    where = torch.rand(D, 60, generator=g) > 0.3
    weights = torch.randn(D, 3, 60, generator=g, dtype=torch.float64)
    results = []
    for dtype in (torch.float32, torch.float64):
        vc = ViewColour(2, (6, 8), frame.grid_from_camera(dtype), 0.1, photo.to(dtype)).to(dtype)
        with torch.no_grad():
            vc.texture.copy_(torch.randn(vc.texture.shape, generator=torch.Generator().manual_seed(2)))
        out = vc.logits(grid.to(dtype), dirs.to(dtype), [0, 2, D], where)
        (grad,) = torch.autograd.grad((out * weights.to(dtype)).sum(), [vc.texture])
        results.append((out.detach().double(), grad.double()))
    assert 0 < float((vc.mask == 0).double().mean()) < 0.6  # the textured half's texels, some of them
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(results[0][1], results[1][1], rtol=1e-4, atol=1e-4)
    for out, _ in results:
        assert bool((out[~where[:, None].expand(-1, 3, -1)] == 0).all())
        assert bool((out[:, :, 50:] == 0).all())  # no direction into the planes, or no parallax
    assert float(results[0][0].abs().max()) > 0.1 and float(results[0][1].abs().max()) > 0.1
    assert float(results[0][1][:, :, :, -1].abs().max()) == 0  # texels on the textured right learn nothing


def test_flatness_is_one_on_a_flat_photo_part_and_falls_with_the_gradient() -> None:
    """A photo flat on its left, a ramp of 0.01 grey levels per pixel in the middle (1 / e where
    the whole texel lies on it) and noise on its right."""
    g = torch.Generator().manual_seed(3)
    photo = torch.full((3, 48, 64), 0.4)
    photo[:, :, 16:48] = 0.4 + 0.01 * torch.arange(32.0)  # texel columns 2-5
    photo[:, :, 48:] = torch.rand(3, 48, 16, generator=g)  # columns 6 and 7
    mask = flatness(photo, (6, 8))  # 8 x 8 pixels a texel; the image border's gradient counts 0
    assert float(mask[:, :2].min()) > 0.99
    torch.testing.assert_close(mask[1:-1, 3:5], torch.full((4, 2), math.exp(-1)))
    assert float(mask[:, 6:].max()) < 1e-3


def test_bakes_and_the_reference_camera_leave_the_view_colour_out() -> None:
    """A field whose ViewColour texture is far from 0 bakes as the same field without it and
    renders the same from its reference camera, but not from a moved camera."""
    frame, vc = _view_colour(torch.float32)
    with torch.no_grad():
        vc.texture.normal_(0, 3, generator=torch.Generator().manual_seed(4))
    plain = random_pyramid(5, torch.float32)
    with_term = random_pyramid(5, torch.float32)
    with_term.view_colour = vc
    h, w = frame.extent
    g, dirs = texel_grid(h, w), torch.zeros(h * w, 3)
    with torch.no_grad():
        assert torch.equal(plain.on_texel_grid(g, frame.plane_z, dirs), with_term.on_texel_grid(g, frame.plane_z, dirs))
        for target, same in (("reference", True), ("moved", False)):
            K_t, P_t = (torch.as_tensor(a, dtype=torch.float32) for a in target_cameras()[target])
            a, b = (render_rays(f, frame, K_t, P_t, pixel_centers(W, H)).rgb for f in (plain, with_term))
            assert (float((a - b).abs().max()) < 1e-5) == same, target
