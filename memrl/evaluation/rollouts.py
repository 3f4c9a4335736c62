"""Fig. 7: strips of scene pictures at chosen steps of evaluation episodes, and MP4 videos.

An episode of the protocol is replayed from its scene seed with the evaluated policy
(rebuilt from ``eval.json``): the same episode as in the evaluation, so the strip shows
what the scores counted. People (``human``) cannot be replayed and are skipped.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from hydra.utils import instantiate

from memrl.checkpoint import load_qnet
from memrl.envs.lane_change import LaneChangeEnv
from memrl.envs.vehicles import ACTIONS
from memrl.evaluation.policies import GreedyActor, PolicySource
from memrl.evaluation.protocol import EpisodeRecord, ProtocolConfig, protocol_env
from memrl.evaluation.results import EvalResult
from memrl.evaluation.runner import Actor, Job, run_job

log = logging.getLogger(__name__)

WHITE, BLACK = (255, 255, 255), (0, 0, 0)
FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass
class Capture:
    """Everything shown of one replayed episode; index 0 is the state after the reset."""

    record: EpisodeRecord
    scenes: list[np.ndarray] = field(default_factory=list)
    """Full-scene RGB pictures ``(H, W, 3)``, one per step."""
    views: list[np.ndarray] = field(default_factory=list)
    """The agent's newest grayscale frame ``(84, 84)``, one per step."""
    actions: list[int] = field(default_factory=list)
    """Action taken before each picture (none before the first)."""
    reached_at: int | None = None
    """First step at which the agent was wholly inside the target lane."""


def actor_for(result: EvalResult) -> Actor | None:
    """The evaluated policy, rebuilt from ``eval.json`` (None for a human)."""
    kind = result.meta.get("kind")
    if kind == "checkpoint":  # the run as recorded, or the one holding this eval folder (moved runs)
        run = Path(result.meta["run"])
        return GreedyActor(load_qnet(run if run.exists() else result.path.parent)[0])
    if kind in ("driver", "python", "sb3") and result.meta.get("policy_config"):  # made from config
        source: PolicySource = instantiate(result.meta["policy_config"])
        return source.candidates()[0].actor
    return None


def capture(actor: Actor, result: EvalResult, initial_lane: str, episode: int) -> Capture:
    """Replay episode ``episode`` of ``initial_lane`` and keep its pictures."""
    protocol = ProtocolConfig(**result.protocol)
    env_cfg = protocol_env(result.env, protocol, initial_lane)
    cap: dict[str, Capture] = {}
    scenes: list[np.ndarray] = []
    views: list[np.ndarray] = []
    actions: list[int] = []
    reached: list[int] = []

    def hook(env: LaneChangeEnv, pixels: np.ndarray, action: int | None, rec: EpisodeRecord | None) -> None:
        scenes.append(env.render())  # type: ignore[arg-type]
        views.append(pixels[-1].copy())
        if action is not None:
            actions.append(action)
        if env.reached_target and not reached:
            reached.append(env.steps)
        if rec is not None:
            cap["done"] = Capture(rec, scenes, views, actions, reached[0] if reached else None)

    run_job(actor, Job(env_cfg, initial_lane, [(episode, result.seeds[episode])]), batch=1, hook=hook)
    return cap["done"]


def successes(result: EvalResult, initial_lane: str) -> list[int]:
    """Episodes that survived and reached the target lane from another lane (a real change)."""
    return [r.episode for r in result.records() if r.initial_lane == initial_lane
            and r.survived and r.goal and not r.started_on_target]


def pick_episodes(result: EvalResult, initial_lane: str, count: int, how: str = "success") -> list[int]:
    """Episode indices to show: ``success``: the first that survived and reached the target
    lane from another lane (a real lane change), filled up with the first others; ``first``:
    episodes 0, 1, ..."""
    if how not in ("success", "first"):
        raise ValueError(f"rollouts 'pick': expected success or first, got {how!r}")
    recs = [r for r in result.records() if r.initial_lane == initial_lane]
    good = successes(result, initial_lane) if how == "success" else []
    rest = [r.episode for r in recs if r.episode not in good]
    return (good + rest)[:count]


def _label(img: np.ndarray, text: str, height: int = 22, scale: float = 0.45) -> np.ndarray:
    """The picture with a white band below it holding ``text``."""
    band = np.full((height, img.shape[1], 3), 255, np.uint8)
    cv2.putText(band, text, (4, height - 7), FONT, scale, BLACK, 1, cv2.LINE_AA)
    return np.concatenate([img, band])


def _outcome(c: Capture) -> str:
    r = c.record
    end = f"collision at step {r.steps}" if r.collided else f"no collision in {r.steps} steps"
    goal = f"target lane at step {c.reached_at}" if c.reached_at is not None else "target lane not reached"
    return f"scene seed {r.seed}, {r.vehicles} car{'' if r.vehicles == 1 else 's'}: {end}; {goal}"


def auto_steps(c: Capture, n: int = 5, after: int = 30) -> list[int]:
    """``n`` evenly spaced steps from the start to ``after`` steps past the lane change (or
    to the end of the episode when there is none, or it comes first)."""
    end = len(c.scenes) - 1
    stop = min(end, c.reached_at + after) if c.reached_at else end
    return sorted({int(round(x)) for x in np.linspace(0, stop, n)})


LEGEND = (("agent", "agent"), ("constant", "other car (constant speed)"),
          ("learned", "other car (past agent)"), ("target_lane", "target lane"), ("road", "road"))
"""Colour legend of the scene pictures: (palette shade, meaning)."""


def _band(width: int, text: str, height: int = 24, color: tuple[int, int, int] = BLACK,
          scale: float = 0.45) -> np.ndarray:
    band = np.full((height, width, 3), 255, np.uint8)
    cv2.putText(band, text, (4, height - 7), FONT, scale, color, 1, cv2.LINE_AA)
    return band


def legend(width: int, height: int = 24) -> np.ndarray:
    """A white band with a coloured swatch and the meaning of each scene colour."""
    from memrl.envs.render import PALETTE

    band = np.full((height, max(width, 10), 3), 255, np.uint8)
    x = 4
    for shade, text in LEGEND:
        cv2.rectangle(band, (x, 5), (x + 14, height - 6), PALETTE[shade], -1)
        cv2.rectangle(band, (x, 5), (x + 14, height - 6), BLACK, 1)
        cv2.putText(band, text, (x + 19, height - 8), FONT, 0.4, BLACK, 1, cv2.LINE_AA)
        x += 19 + cv2.getTextSize(text, FONT, 0.4, 1)[0][0] + 14
    return band


def strip(captures: Sequence[Capture], steps: Sequence[int] | None = None, scale: float = 1.0,
          gap: int = 6, title: str | None = None, note: str | None = None) -> np.ndarray:
    """One row per episode: scene pictures at ``steps`` (the last one when the episode ended
    earlier; None: :func:`auto_steps` per episode), labelled like the paper's Fig. 7, under
    ``title`` (method and seed) and ``note`` (in red, e.g. that no episode succeeded), over a
    colour legend; RGB."""
    rows = []
    for i, c in enumerate(captures):
        tiles = []
        for step in steps if steps is not None else auto_steps(c):
            k = min(step, len(c.scenes) - 1)
            img = cv2.resize(c.scenes[k], None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            name = "initial" if k == 0 else f"step {k}" + (" (end)" if k < step else "")
            tiles.append(_label(img, name))
            tiles.append(np.full((tiles[-1].shape[0], gap, 3), 255, np.uint8))
        row = np.concatenate(tiles[:-1], axis=1)
        caption = np.full((24, row.shape[1], 3), 255, np.uint8)
        cv2.putText(caption, f"({chr(97 + i)}) {_outcome(c)}", (4, 17), FONT, 0.42, BLACK, 1, cv2.LINE_AA)
        rows += [caption, row, np.full((gap, row.shape[1], 3), 255, np.uint8)]
    width = max(r.shape[1] for r in rows)
    head = ([_band(width, title, 28, scale=0.55)] if title else []) + \
        ([_band(width, note, 24, (200, 0, 0))] if note else [])
    rows = [*head, *rows, legend(width)]
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    return np.concatenate(rows)


def write_png(img: np.ndarray, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")
    return path


def video_frame(c: Capture, k: int, view_scale: int = 4) -> np.ndarray:
    """Scene picture, the agent's view enlarged, and the step's numbers, side by side (RGB)."""
    scene = c.scenes[k]
    view = cv2.resize(c.views[k], None, fx=view_scale, fy=view_scale, interpolation=cv2.INTER_NEAREST)
    h = max(scene.shape[0], view.shape[0] + 90) + 20
    w = scene.shape[1] + view.shape[1] + 30
    frame = np.full((h + h % 2, w + w % 2, 3), 30, np.uint8)  # even sizes for the codec
    frame[10:10 + scene.shape[0], 10:10 + scene.shape[1]] = scene
    x0 = scene.shape[1] + 20
    frame[10:10 + view.shape[0], x0:x0 + view.shape[1]] = view[:, :, None]
    ds, dk = ACTIONS[c.actions[k - 1]] if k > 0 else (0, 0)
    lines = [f"step {k}/{c.record.steps}", f"action: speed {ds:+d}, curvature {dk:+d}" if k else "start",
             "target lane reached" if c.reached_at is not None and k >= c.reached_at else ""]
    for j, text in enumerate(lines):
        cv2.putText(frame, text, (x0, 10 + view.shape[0] + 25 + 22 * j), FONT, 0.55, WHITE, 1, cv2.LINE_AA)
    return frame


def write_rgb_video(frames: Sequence[np.ndarray], path: Path, fps: float = 10.0) -> Path:
    """H.264 MP4 (``yuv420p``, index at the front) of RGB frames of one even size: the codec
    browsers, GitHub and notebooks play."""
    # imageio-ffmpeg: a static ffmpeg with libx264 from pip; OpenCV's wheels write only mp4v.
    import imageio_ffmpeg

    h, w = frames[0].shape[:2]
    if h % 2 or w % 2:
        raise ValueError(f"H.264 (yuv420p) needs even frame sizes, got {w}x{h}")
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = imageio_ffmpeg.write_frames(
        str(path), (w, h), fps=fps, codec="libx264", pix_fmt_in="rgb24", pix_fmt_out="yuv420p",
        quality=None, macro_block_size=2, output_params=["-crf", "20", "-movflags", "+faststart"])
    try:
        writer.send(None)  # start ffmpeg
        for f in frames:
            writer.send(np.ascontiguousarray(f, dtype=np.uint8))
    except (OSError, RuntimeError) as e:
        raise OSError(f"could not write the video {path} ({e})") from None
    finally:
        writer.close()
    return path


def write_video(captures: Sequence[Capture], path: Path, fps: float = 10.0, hold: int = 10) -> Path:
    """H.264 MP4 (:func:`write_rgb_video`) of whole episodes one after another; the last
    picture of each is held for ``hold`` frames."""
    frames = [video_frame(c, k) for c in captures for k in
              [*range(len(c.scenes)), *([len(c.scenes) - 1] * hold)]]
    return write_rgb_video(frames, path, fps)
