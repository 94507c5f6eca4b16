"""`gear render OUT_DIR --t 0 0.5 1`: images of the trained twin at any articulation state.

Cameras orbit the object (the sphere holding it at every requested state) at a fixed elevation
about `--up`; `--frames K` adds an animation: K frames sweeping the state from start to end
while the camera turns once around, saved as PNG frames, a strip and a GIF. `--video FILE`
writes a video (H.264 through imageio's ffmpeg): start -> end -> start while the camera turns
once around, so it loops seamlessly.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from gear.camera import Camera

FOV_X = np.deg2rad(40.0)
ELEVATION_DEG = 25.0  # default camera elevation above the orbit plane
MARGIN = 1.15  # the object's bounding sphere fills the view with this much room
_AXES = {"x": 0, "y": 1, "z": 2}
VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov")  # containers that hold H.264
UP_CHOICES = ["x", "y", "z", "-x", "-y", "-z"]
# --color parts: static part grey, movable parts in distinct hues (cycled past 9 parts).
PART_PALETTE = np.array([
    [0.6, 0.6, 0.6], [0.89, 0.1, 0.11], [0.22, 0.49, 0.72], [0.3, 0.69, 0.29],
    [0.6, 0.31, 0.64], [1.0, 0.5, 0.0], [0.65, 0.34, 0.16], [0.97, 0.51, 0.75],
    [0.1, 0.75, 0.8], [0.9, 0.8, 0.1],
], dtype=np.float32)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="render the trained twin at intermediate states")
    p.add_argument("out_dir", type=Path, help="a trained run's output folder")
    p.add_argument("--t", type=float, nargs="+", default=None, metavar="S",
                   help="states to render: 0 = start, 1 = end (default: 0 0.5 1, or none when "
                        "only --video is asked for)")
    p.add_argument("--views", type=int, default=8, help="orbit cameras per state (default 8)")
    p.add_argument("--res", type=int, default=256, help="image width and height (default 256)")
    p.add_argument("--frames", type=int, default=0, metavar="K",
                   help="also write a K-frame start->end animation with a turning camera")
    p.add_argument("--video", type=Path, default=None, metavar="FILE",
                   help="also write a video (.mp4, .mkv or .mov): start -> end -> start with "
                        "the camera turning once around")
    p.add_argument("--fps", type=int, default=24, help="video frame rate (default 24)")
    p.add_argument("--duration", type=float, default=4.0, metavar="SEC",
                   help="video length in seconds (default 4)")
    p.add_argument("--size", type=int, nargs=2, default=[512, 512], metavar=("W", "H"),
                   help="video frame width and height, even numbers (default 512 512)")
    p.add_argument("--elevation", type=float, default=ELEVATION_DEG,
                   help=f"camera elevation above the orbit plane, degrees (default "
                        f"{ELEVATION_DEG:g})")
    p.add_argument("--up", default="z", choices=UP_CHOICES,
                   help="world axis the orbit turns about (default z)")
    p.add_argument("--color", choices=["rgb", "parts"], default="rgb",
                   help="rgb (the trained colours) or parts (a flat colour per part: grey "
                        "static, then red, blue, green, ... for joints[0], joints[1], ...)")
    p.add_argument("--background", type=float, nargs=3, default=[1.0, 1.0, 1.0],
                   metavar=("R", "G", "B"), help="background colour in [0, 1] (default white)")
    p.add_argument("--out", type=Path, default=None,
                   help="output folder (default OUT_DIR/twin_renders)")
    p.set_defaults(handler=run)


def orbit_direction(azimuth_deg: float, elevation_deg: float, up: np.ndarray) -> np.ndarray:
    """Unit vector from the orbit centre to a camera at this azimuth (about `up`) and elevation."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    ahead = np.cross(up, side)
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    return np.cos(el) * (np.cos(az) * side + np.sin(az) * ahead) + np.sin(el) * up


def fit_distance(radius: float, fov: float) -> float:
    """Camera distance at which a sphere of `radius` fills a view of angle `fov` (radians),
    with MARGIN room."""
    return MARGIN * radius / np.sin(fov / 2)


def orbit_cameras(center: np.ndarray, radius: float, azimuths_deg: np.ndarray,
                  elevation_deg: float, up: np.ndarray, res: int,
                  height: int | None = None) -> list[Camera]:
    """Cameras `res` wide (and `height` tall, default square) looking at `center` from the
    given azimuths, far enough for a sphere of `radius` to fit the narrower side of the view."""
    height = res if height is None else height
    fov_y = 2 * np.arctan(np.tan(FOV_X / 2) * height / res)
    distance = fit_distance(radius, min(FOV_X, fov_y))
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    return [Camera.look_at(center + distance * orbit_direction(az, elevation_deg, up), center,
                           up, FOV_X, res, height)
            for az in np.asarray(azimuths_deg, dtype=np.float64)]


def part_colors(parts: np.ndarray) -> np.ndarray:
    """[N,3] float32 flat colour of each part id: static grey, then PART_PALETTE's hues."""
    parts = np.asarray(parts)
    hues = len(PART_PALETTE) - 1
    return PART_PALETTE[np.where(parts == 0, 0, 1 + (parts - 1) % hues)]


def up_vector(name: str) -> np.ndarray:
    """The unit world axis of an `--up` choice ("z", "-y", ...)."""
    up = np.zeros(3)
    up[_AXES[name[-1]]] = -1.0 if name.startswith("-") else 1.0
    return up


def _image(rgb: torch.Tensor) -> Image.Image:
    """uint8 image of a rendered [H,W,3] colour (already over the background)."""
    rgb = rgb.numpy()
    if not np.all(np.isfinite(rgb)):  # never write a silently broken image
        raise RuntimeError("the renderer returned non-finite pixels")
    return Image.fromarray(np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8))


def video_path(states: int) -> tuple[np.ndarray, np.ndarray]:
    """(states [n], azimuths in degrees [n]) of an n-frame loop: the state goes linearly from
    0 up to 1 at the middle frame and back (the frame after the last is the first again)
    while the camera turns once around."""
    phase = np.arange(states) / states
    return 1.0 - np.abs(1.0 - 2.0 * phase), 360.0 * phase


def _write_video(path: Path, frames: Iterable[Image.Image], count: int, fps: int) -> None:
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    # yuv420p: the pixel format every player decodes; macro_block_size=1 keeps the exact size.
    with imageio.get_writer(path, format="FFMPEG", mode="I", fps=fps, codec="libx264",
                            pixelformat="yuv420p", macro_block_size=1, quality=8) as writer:
        for frame in tqdm(frames, total=count, desc="video", unit="frame", leave=False):
            writer.append_data(np.asarray(frame))


def _check_args(args: argparse.Namespace) -> None:
    from gear.cli import UserError

    for name, value, low in (("--views", args.views, 1), ("--res", args.res, 8),
                             ("--frames", args.frames, 0), ("--fps", args.fps, 1)):
        if value < low:
            raise UserError(f"{name} must be at least {low}, got {value}")
    if any(not 0.0 <= s <= 1.0 for s in args.t):
        raise UserError(f"--t: states must be in [0, 1] (0 = start, 1 = end), got {args.t}")
    if any(not 0.0 <= c <= 1.0 for c in args.background):
        raise UserError(f"--background: colour components must be in [0, 1], got "
                        f"{args.background}")
    if args.video is not None:
        if args.video.suffix.lower() not in VIDEO_SUFFIXES:
            raise UserError(f"--video {args.video}: the file must end in one of "
                            f"{', '.join(VIDEO_SUFFIXES)}")
        if any(v < 16 or v % 2 for v in args.size):
            raise UserError(f"--size: width and height must be even and at least 16 (H.264), "
                            f"got {args.size[0]} {args.size[1]}")
        if not (np.isfinite(args.duration) and args.duration * args.fps >= 2):
            raise UserError(f"--duration {args.duration} at --fps {args.fps} gives fewer than "
                            "2 frames")


def run(args: argparse.Namespace) -> int:
    from gear.run_folder import require_finished
    from gear.twin import Twin

    if args.t is None:
        args.t = [] if args.video is not None else [0.0, 0.5, 1.0]
    _check_args(args)
    twin = Twin.load(require_finished(args.out_dir))
    out_dir = args.out or args.out_dir / "twin_renders"
    up = up_vector(args.up)
    background = torch.tensor(args.background, dtype=torch.float32)
    sweep = list(np.linspace(0.0, 1.0, max(args.frames, 2)))
    count = round(args.duration * args.fps) if args.video is not None else 0
    states, azimuths = video_path(count)
    center, radius = twin.bounds(sorted(set(args.t) | set(sweep) | set(states.tolist())))
    colors = None
    if args.color == "parts":
        colors = torch.as_tensor(part_colors(twin.parts.numpy()))

    def shot(s: float, cam: Camera) -> Image.Image:
        return _image(twin.render(s, cam, background, colors=colors).features)

    cams = orbit_cameras(center, radius, np.arange(args.views) * 360.0 / args.views,
                         args.elevation, up, args.res)
    for s in args.t:
        folder = out_dir / f"s{s:.3f}"
        folder.mkdir(parents=True, exist_ok=True)
        for v, cam in enumerate(cams):
            shot(s, cam).save(folder / f"{v:03d}.png")
    if args.t:
        print(f"rendered {len(args.t)} state(s) x {args.views} view(s) at {args.res}x"
              f"{args.res} into {out_dir}")

    if args.frames:
        states = sweep if args.frames > 1 else [0.0]
        cams = orbit_cameras(center, radius, np.arange(args.frames) * 360.0 / args.frames,
                             args.elevation, up, args.res)
        folder = out_dir / "animation"
        folder.mkdir(parents=True, exist_ok=True)
        frames = [shot(s, cam) for s, cam in zip(states, cams, strict=True)]
        for k, frame in enumerate(frames):
            frame.save(folder / f"{k:04d}.png")
        strip = Image.new("RGB", (args.res * len(frames), args.res))
        for k, frame in enumerate(frames):
            strip.paste(frame, (k * args.res, 0))
        strip.save(folder / "strip.png")
        frames[0].save(folder / "animation.gif", save_all=True, append_images=frames[1:],
                       duration=80, loop=0)
        print(f"animation: {args.frames} frame(s), strip.png and animation.gif in {folder}")

    if args.video is not None:
        width, height = args.size
        cams = orbit_cameras(center, radius, azimuths, args.elevation, up, width, height)
        _write_video(args.video, (shot(s, cam) for s, cam in zip(states, cams, strict=True)),
                     count, args.fps)
        print(f"video: {count} frame(s) at {args.fps} fps, {width}x{height}, start -> end -> "
              f"start, in {args.video}")
    return 0
