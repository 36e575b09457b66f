"""``mkv play``: render an episode of a policy, in a window or as frames (PNG files or a GIF).

::

    mkv play --policy SPEC [--env ID] [--seed S] [--max-steps N] [--out FRAMES_DIR | OUT.gif]

Without a display the frames go to ``play_frames/``.
"""

from __future__ import annotations

import argparse
import os

from sfm_common.files import atomic_path
from sfm_learn.cli.common import (
    POLICY_HELP,
    CliError,
    add_env_arguments,
    add_trust_argument,
    apply_trust,
    check_env_and_policies,
    check_output_path,
    positive_int,
    seed,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_env_arguments(p)
    p.add_argument("--policy", required=True, metavar="SPEC", help=POLICY_HELP)
    p.add_argument("--seed", type=seed, default=0, metavar="S",
                   help="env seed of the episode; the policy's seed is derived from it "
                        "(default 0)")
    p.add_argument("--max-steps", type=positive_int, default=None, metavar="N",
                   help="stop after N steps (default: the episode's own end)")
    p.add_argument("--out", metavar="DIR|OUT.gif|OUT.mp4",
                   help="write frames (PNG files in DIR, one animated GIF, or an MP4 video "
                        "through gymnasium's RecordVideo, which needs moviepy) instead of a "
                        "window; the default without a display is play_frames/")
    add_trust_argument(p)


def run(args) -> int:
    apply_trust(args)
    from mkv_env.policies import make_policy
    from mkv_env.recorder import make_env, policy_seed
    from mkv_env.teleop import has_display

    out = args.out
    if out is None and not has_display():
        out = "play_frames"
    gif = out is not None and out.lower().endswith(".gif")
    mp4 = out is not None and out.lower().endswith(".mp4")
    if out is not None:
        if gif or mp4:
            check_output_path(out)
        elif os.path.exists(out) and not os.path.isdir(out):
            raise CliError(f"frames directory {out} exists and is not a directory")
    if gif:
        try:
            import PIL.Image  # noqa: F401  (only to write GIFs)
        except ImportError:
            raise CliError("writing a GIF needs Pillow; give a directory for PNG frames") from None
    if mp4:
        try:
            import moviepy  # noqa: F401  (RecordVideo writes MP4 through it)
        except ImportError:
            raise CliError("writing an MP4 needs moviepy (pip install moviepy, or the project's "
                           "[zoo] extra); give .gif or a directory instead") from None
    check_env_and_policies(args.env, args.env_kwargs, [args.policy])
    try:
        import pygame  # noqa: F401
    except ImportError:
        raise CliError("mkv play needs pygame (pip install 'mkv-sfm[render]')") from None

    env = make_env(args.env, args.env_kwargs, render_mode="rgb_array" if out else "human")
    video_dir = None
    if mp4:
        import tempfile

        from gymnasium.wrappers import RecordVideo

        scratch = tempfile.mkdtemp(prefix=".mkv-play-", dir=os.path.dirname(
            os.path.abspath(out)))
        video_dir = os.path.join(scratch, "video")  # new: RecordVideo warns on an existing one
        env = RecordVideo(env, video_dir, episode_trigger=lambda e: e == 0, name_prefix="run",
                          disable_logger=True)
    frames = []
    try:
        policy = make_policy(args.policy, env, seed=policy_seed(args.seed))
        if hasattr(policy, "reset"):
            policy.reset(seed=policy_seed(args.seed))
        obs, info = env.reset(seed=args.seed)
        if out and not mp4:
            frames.append(env.render())
        steps, ret, start, state = 0, 0.0, True, None
        while True:
            # hand the returned state back, as the recorder does (recurrent policies keep memory)
            action, state = policy.predict(obs, state=state, episode_start=start)
            start = False
            obs, reward, terminated, truncated, info = env.step(action)
            ret += float(reward)
            steps += 1
            if out and not mp4:
                frames.append(env.render())
            if terminated or truncated or (args.max_steps and steps >= args.max_steps):
                break
    finally:
        env.close()  # RecordVideo writes its file here
        if video_dir is not None:
            videos = (sorted(f for f in os.listdir(video_dir) if f.endswith(".mp4"))
                      if os.path.isdir(video_dir) else [])
            if videos:
                os.replace(os.path.join(video_dir, videos[0]), out)
            import shutil

            shutil.rmtree(os.path.dirname(video_dir), ignore_errors=True)
    summary = f"{steps} steps, return {ret:.2f}, distance {info['distance_m']:.2f} m"
    if "escaped" in info:
        summary += ", escaped" if info["escaped"] else ", not escaped"
    print(summary)
    if mp4:
        print(f"wrote {steps + 1} frames to {out} (gymnasium RecordVideo)")
    elif out:
        written = _write_gif(frames, out, env.metadata.get("render_fps", 10)) if gif \
            else _write_pngs(frames, out)
        print(f"wrote {written}")
    return 0


def _write_pngs(frames, directory: str) -> str:
    import numpy as np
    import pygame

    os.makedirs(directory, exist_ok=True)
    width = max(4, len(str(len(frames))))
    for i, frame in enumerate(frames):
        surface = pygame.surfarray.make_surface(np.ascontiguousarray(frame.transpose(1, 0, 2)))
        pygame.image.save(surface, os.path.join(directory, f"frame_{i:0{width}d}.png"))
    return f"{len(frames)} PNG frames to {directory}"


def _write_gif(frames, path: str, fps: int) -> str:
    from PIL import Image

    images = [Image.fromarray(f) for f in frames]
    with atomic_path(path, ".gif") as tmp:
        images[0].save(tmp, save_all=True, append_images=images[1:],
                       duration=max(1, round(1000 / fps)), loop=0)
    return f"{len(frames)} frames to {path}"
