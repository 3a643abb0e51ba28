"""Videos of reaches: the arm in MuJoCo's offscreen renderer (headless: EGL or OSMesa),
the active subgoal with its admission sphere, the goal and the fingertip's trail drawn,
time and goal error overlaid. MP4 through PyAV (``pip install 'dammrl[video]'``) or an
animated GIF through Pillow (no extra: small enough for documentation).

A video is made from a :class:`Track` (what the arm did, over time), taken from an
in-process reach or from a recording, so both look the same.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dammrl.stack.runner import ReachResult, ReachRunner
from dammrl_core.errors import ConfigurationError, JobFailedError
from schemas import EpisodeResult, RobotState, StepEvent, TaskGoal

TRAIL_POINTS = 60  # fingertip trail: this many markers over the last TRAIL_S
TRAIL_S = 3.0
SUBGOAL_RGBA = (0.1, 0.5, 1.0, 0.35)
GOAL_RGBA = (0.1, 0.8, 0.2, 0.9)
TRAIL_RGBA = (1.0, 0.55, 0.0, 0.8)
TABLE_RGBA = (0.55, 0.45, 0.35, 0.4)  # see-through: the elbow may dip below the top
LINK_RGBA = (0.75, 0.75, 0.8, 1.0)
JOINT_RGBA = (0.35, 0.35, 0.4, 1.0)


@dataclass(frozen=True)
class Track:
    """What the arm did: samples at times ``t`` [s] (increasing)."""

    t: np.ndarray  # (N,)
    q: np.ndarray  # (N, 6) joint positions [rad]
    ee: np.ndarray  # (N, 3) end-effector [m]
    subgoal: np.ndarray  # (N, 3) active subgoal [m], NaN before the first step
    radius: np.ndarray  # (N,) its admission radius [m]
    button_travel: np.ndarray  # (N,) how far the cap is pressed [m]
    goal: np.ndarray  # (3,)
    label: str  # e.g. "seed 7000001, event, M_2,1"
    outcome: str = ""  # e.g. "success in 7.42 s", shown once it happened
    end_s: float = float("inf")  # when the outcome happened [s, on t]


def track_of_reach(result: ReachResult) -> Track:
    """The track of an in-process reach, up to its end."""
    traj, m = result.trajectory, result.metrics
    keep = traj.t <= m.t_total_s + 0.5  # the reach and half a second of its hold
    outcome = f"{'success' if m.success else m.outcome} in {m.t_total_s:.2f} s"
    label = f"seed {result.seed}, {result.trigger}, M_{result.model[0]},{result.model[1]}"
    travel = np.zeros(int(keep.sum()))
    if m.button_pressed:  # the log keeps no travel: show the cap down from the press on
        travel[traj.t[keep] >= m.t_total_s - 0.1] = 0.008
    return Track(traj.t[keep], traj.q[keep], traj.x[keep], traj.subgoal[keep],
                 traj.radius[keep], travel, result.task.goal, label, outcome,
                 m.t_total_s)  # fmt: skip


def track_of_recording(path: Path, episode: int | None = None) -> Track:
    """The track of one episode of a recording (default: the first with robot states)."""
    from dammrl.stack.recording import read_recording

    goals: dict[int, TaskGoal] = {}
    states: list[RobotState] = []
    steps: list[StepEvent] = []
    result: EpisodeResult | None = None
    for _, message in read_recording(path).decoded(TaskGoal, RobotState, StepEvent, EpisodeResult):
        if isinstance(message, TaskGoal):
            goals.setdefault(message.episode, message)
            if episode is None and not states:
                episode = message.episode
        elif getattr(message, "episode", None) != episode:
            continue
        elif isinstance(message, RobotState):
            states.append(message)
        elif isinstance(message, StepEvent):
            steps.append(message)
        elif isinstance(message, EpisodeResult):
            result = message
    if episode not in goals or len(states) < 2:
        raise JobFailedError(f"{path}: no episode {episode or ''} with a goal and robot states")
    return _track(states, steps, goals[episode], result)


def _track(states: list[RobotState], steps: list[StepEvent], goal: TaskGoal,
           result: EpisodeResult | None) -> Track:  # fmt: skip
    states = sorted(states, key=lambda s: s.t_s)
    t = np.array([s.t_s for s in states])
    subgoal, radius = np.full((len(t), 3), np.nan), np.zeros(len(t))
    for step in sorted(steps, key=lambda s: s.start_s):
        after = t >= step.start_s
        subgoal[after], radius[after] = step.subgoal_m, step.radius_m
    outcome, end_s = "", float("inf")
    if result is not None:
        outcome = f"{'success' if result.success else result.outcome} in {result.t_total_s:.2f} s"
        end_s = result.t_total_s  # the episode's clock starts with its first state
    return Track(
        t - t[0],
        np.array([s.q_rad for s in states]),
        np.array([s.ee_pos_m for s in states]),
        subgoal,
        radius,
        np.clip([s.button_travel_m for s in states], 0, None),
        np.array(goal.goal_m),
        f"episode {goal.episode}",
        outcome,
        end_s,
    )


@dataclass(frozen=True)
class VideoSettings:
    fps: int = 25
    width: int = 640
    height: int = 480
    speed: float = 1.0  # playback speed (2: twice real time)

    def check(self) -> None:
        if not (1 <= self.fps <= 120 and 64 <= self.width <= 3840 and 64 <= self.height <= 2160
                and 0.05 <= self.speed <= 50):  # fmt: skip
            raise ConfigurationError(
                "video: fps 1-120, width 64-3840, height 64-2160, speed 0.05-50"
            )


OUTCOME_SHOWN_S = 1.0
"""How long a video goes on (the arm still) once its episode ended, its outcome shown [s]."""


def frame_times(track: Track, video: VideoSettings) -> np.ndarray:
    """The track times shown by each frame: to its last sample, and on to show the
    outcome for ``OUTCOME_SHOWN_S`` when the episode ended (a track ends at its end)."""
    last = float(track.t[-1])
    if math.isfinite(track.end_s):
        last = max(last, track.end_s + OUTCOME_SHOWN_S)
    duration = last - float(track.t[0])
    count = max(1, math.floor(duration / video.speed * video.fps) + 1)
    return np.asarray(track.t[0] + np.arange(count) * video.speed / video.fps)


def frames(track: Track, video: VideoSettings, runner: ReachRunner | None = None
           ) -> Iterator[np.ndarray]:  # fmt: skip
    """RGB frames (height, width, 3) of the track, rendered offscreen."""
    import mujoco

    runner = runner or ReachRunner()
    model, data = runner.sim.model, runner.sim.data
    runner.sim.reset(track.q[0], (float(track.goal[0]), float(track.goal[1])))
    try:
        renderer = mujoco.Renderer(model, video.height, video.width)
    except Exception as exc:  # no GL context: say what to install
        raise JobFailedError(
            f"no headless OpenGL for MuJoCo ({exc}): install libegl1 (MUJOCO_GL=egl) or "
            "libosmesa6 (MUJOCO_GL=osmesa)"
        ) from None
    camera = _camera(track)
    with renderer:
        for t in frame_times(track, video):
            k = int(np.clip(np.searchsorted(track.t, t, side="right") - 1, 0, len(track.t) - 1))
            data.qpos[:6] = [np.interp(t, track.t, track.q[:, j]) for j in range(6)]
            data.qpos[6] = -float(track.button_travel[k])
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera)
            _draw_arm(renderer.scene, data, runner)
            _decorate(renderer.scene, track, k, t)
            yield _overlay(renderer.render(), track, k, t)


def _camera(track: Track) -> object:
    import mujoco

    camera = mujoco.MjvCamera()
    camera.lookat[:] = (track.ee[0] + track.goal) / 2
    camera.lookat[2] = max(camera.lookat[2], -0.15)
    camera.distance = 0.75
    camera.azimuth, camera.elevation = 150.0, -25.0
    return camera


def _draw_arm(scene: object, data: object, runner: ReachRunner) -> None:
    """The table (see-through: the model's elbow may pass below its top, the simulation
    has no table to collide with) and the arm's links as capsules between its joints
    (the model has no visual geometry but the fingertip and the button)."""
    import mujoco

    layout = runner.sim.layout
    centre = np.array([*layout.table_center_xy_m, layout.table_top_z_m - 0.01])
    _geom(scene, mujoco.mjtGeom.mjGEOM_BOX, np.array([*layout.table_half_size_xy_m, 0.01]),
          centre, TABLE_RGBA)  # fmt: skip
    joints = [data.xpos[b].copy() for b in range(1, runner.sim.model.nbody)  # type: ignore[attr-defined]
              if runner.sim.model.body(b).name not in ("button", "button_cap")]  # fmt: skip
    _geom(scene, mujoco.mjtGeom.mjGEOM_BOX, np.full(3, 0.04), joints[0], JOINT_RGBA)  # base
    for start, end in itertools.pairwise(joints):
        if np.linalg.norm(end - start) > 1e-6:
            _geom(scene, mujoco.mjtGeom.mjGEOM_CAPSULE, np.array([0.022, 0.0, 0.0]), start,
                  LINK_RGBA, ends=(start, end))  # fmt: skip
    for joint in joints[:-1]:
        _geom(scene, mujoco.mjtGeom.mjGEOM_SPHERE, np.full(3, 0.03), joint, JOINT_RGBA)


def _geom(scene: object, kind: object, size: np.ndarray, position: np.ndarray,
          rgba: tuple[float, ...], ends: tuple[np.ndarray, np.ndarray] | None = None
          ) -> None:  # fmt: skip
    """Append a decoration geom (a connector between ``ends`` when given)."""
    import mujoco

    if scene.ngeom >= scene.maxgeom:  # type: ignore[attr-defined]
        return
    geom = scene.geoms[scene.ngeom]  # type: ignore[attr-defined]
    mujoco.mjv_initGeom(geom, kind, size, np.asarray(position, float), np.eye(3).ravel(),
                        np.asarray(rgba, np.float32))  # fmt: skip
    if ends is not None:
        mujoco.mjv_connector(geom, kind, float(size[0]), ends[0], ends[1])
    scene.ngeom += 1  # type: ignore[attr-defined]


def _decorate(scene: object, track: Track, k: int, t: float) -> None:
    """The goal, the active subgoal with its admission sphere, the fingertip's trail."""
    _sphere(scene, track.goal, 0.006, GOAL_RGBA)
    if np.all(np.isfinite(track.subgoal[k])) and track.radius[k] > 0:
        _sphere(scene, track.subgoal[k], float(track.radius[k]), SUBGOAL_RGBA)
        _sphere(scene, track.subgoal[k], 0.0015, (*SUBGOAL_RGBA[:3], 1.0))
    recent = np.flatnonzero((track.t <= t) & (track.t >= t - TRAIL_S))
    for index in recent[:: max(1, len(recent) // TRAIL_POINTS)]:
        _sphere(scene, track.ee[index], 0.002, TRAIL_RGBA)


def _sphere(scene: object, centre: np.ndarray, radius: float,
            rgba: tuple[float, ...]) -> None:  # fmt: skip
    import mujoco

    _geom(scene, mujoco.mjtGeom.mjGEOM_SPHERE, np.full(3, radius), centre, rgba)


def _overlay(image: np.ndarray, track: Track, k: int, t: float) -> np.ndarray:
    """Time, distance to the goal and the reach's label, top left."""
    from PIL import Image, ImageDraw

    error_mm = float(np.linalg.norm(track.ee[k] - track.goal)) * 1000
    picture = Image.fromarray(image)
    draw = ImageDraw.Draw(picture)
    outcome = f": {track.outcome}" if track.outcome and t >= track.end_s else ""
    text = f"t = {t:5.2f} s   |x - x_g| = {error_mm:6.1f} mm\n{track.label}{outcome}"
    draw.rectangle((4, 4, 8 + 7 * max(len(line) for line in text.splitlines()), 36),
                   fill=(0, 0, 0))  # fmt: skip
    draw.multiline_text((8, 6), text, fill=(255, 255, 255))
    return np.array(picture)


def write_video(track: Track, path: Path, video: VideoSettings | None = None,
                progress: object = None) -> int:  # fmt: skip
    """Render ``track`` to ``path`` (.mp4 or .gif); the number of frames written."""
    video = video or VideoSettings()
    video.check()
    suffix = path.suffix.lower()
    if suffix not in (".mp4", ".gif"):
        raise ConfigurationError(f"video {path}: the name must end in .mp4 or .gif")
    stream = frames(track, video)
    if callable(progress):
        stream = _counted(stream, progress)
    return _write_mp4(stream, path, video) if suffix == ".mp4" else _write_gif(stream, path, video)


def _counted(stream: Iterator[np.ndarray], progress: object) -> Iterator[np.ndarray]:
    for frame in stream:
        yield frame
        progress(1)  # type: ignore[operator]


def _write_mp4(stream: Iterator[np.ndarray], path: Path, video: VideoSettings) -> int:
    try:
        import av
    except ImportError:
        raise ConfigurationError(
            "MP4 needs PyAV: pip install 'dammrl[video]' (or write a .gif)"
        ) from None
    count = 0
    with av.open(str(path), mode="w") as container:
        encoder = container.add_stream("libx264", rate=video.fps, options={"crf": "28"})
        encoder.width, encoder.height, encoder.pix_fmt = video.width, video.height, "yuv420p"
        for image in stream:
            for packet in encoder.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
            count += 1
        for packet in encoder.encode():
            container.mux(packet)
    return count


def _write_gif(stream: Iterator[np.ndarray], path: Path, video: VideoSettings) -> int:
    from PIL import Image

    pictures = [Image.fromarray(image).quantize(64) for image in stream]
    pictures[0].save(path, save_all=True, append_images=pictures[1:], optimize=True,
                     duration=round(1000 / video.fps), loop=0)  # fmt: skip
    return len(pictures)
