"""Large images: a 4096 x 4096 render with depth exceeds one storage binding of many adapters
(lavapipe's 128 MiB included), so the wgpu executor renders it in bands of rows; both
executors must still give the same images and gradients through torch autograd."""

import torch

from gear import splat
from splat_scenes import ARRAYS, camera, random_scene, relative_l2

BACKGROUND = torch.tensor([0.1, 0.3, 0.6])
SIZE = 4096


def render_and_grads(backend: str) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    # Few Gaussians of a few to a few hundred pixels: the cost is the image, not the scene.
    scene = random_scene(100, 3, 9, 1.0, (-4.5, -3.0)).to(torch.float32, requires_grad=True)
    out = splat.rasterize(*scene.arrays(), camera(SIZE, SIZE), BACKGROUND, True, backend=backend)
    images = [out.features, out.alpha, out.depth]
    # Weights that vary over the image, so every band's gradients count differently.
    rows = torch.linspace(0.5, 1.5, SIZE)[:, None]
    loss = (out.features * rows[..., None]).sum() + (out.alpha * rows).sum()
    loss = loss + 0.1 * (out.depth * rows.flip(0)).sum()
    loss.backward()
    return [img.detach() for img in images], [a.grad for a in scene.arrays()]


def test_4k_frame_with_depth_renders_alike_on_both_executors():
    image_bytes = SIZE * SIZE * 5 * 4
    assert image_bytes > 2**27, "no longer larger than a 128 MiB binding"
    cpu_images, cpu_grads = render_and_grads("cpu")
    gpu_images, gpu_grads = render_and_grads("wgpu")
    assert (cpu_images[1] > 0.01).sum() > 100_000, "too few pixels covered to compare"
    # Among 16M pixels a few sit on the 1/255 alpha cut-off, which the two executors' f32
    # arithmetic decides apart: such a flip moves a value by 1/255 of a feature (<= 1.5) or of
    # a depth (< 6); every other value must agree within 1e-4.
    for name, a, b in zip(("features", "alpha", "depth"), cpu_images, gpu_images, strict=True):
        diff = (a - b).abs()
        flips = (diff > 1e-4).sum().item()
        assert flips <= diff.numel() * 1e-5 and diff.max().item() <= 6 / 255, (name, flips)
    for name, a, b in zip(ARRAYS, cpu_grads, gpu_grads, strict=True):
        assert b.abs().sum() > 0, name
        assert relative_l2(a, b) <= 1e-4, f"d{name}: {relative_l2(a, b):.2e}"
