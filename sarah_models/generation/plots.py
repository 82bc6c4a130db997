"""Pictures of a generated conversation: the top view of the paper's Fig. 5 and a skeleton GIF.

World convention (sarah_data/constants.py): y up, metres, floor (x, z). Both files are written
under a temporary name in the target folder and renamed into place.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

from sarah_data.atomic import atomic_path  # noqa: E402

# Display only: the user is known by a floor position, drawn as a head at this height.
USER_HEAD_HEIGHT = 1.6
FACING_LENGTH = 0.3  # metres, length of the agent's facing ticks in the top view


def save_figure(fig, path: str | Path) -> Path:
    """Write a figure as PNG through a temporary file and a rename, then close it."""
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
    finally:
        plt.close(fig)
    return Path(path)


def _time_line(ax, xz: np.ndarray, cmap: str) -> None:
    segments = np.stack([xz[:-1], xz[1:]], axis=1)
    lines = LineCollection(segments, cmap=cmap, linewidths=2.5, zorder=2)
    lines.set_array(np.linspace(0.0, 1.0, len(segments)))
    ax.add_collection(lines)
    colours = plt.get_cmap(cmap)([0.0, 1.0])
    ax.scatter(*xz[0], color=colours[0], s=40, edgecolor="k", zorder=3)
    ax.scatter(*xz[-1], color=colours[1], s=40, marker="s", edgecolor="k", zorder=3)


def plot_topview(path: str | Path, agent_xz: np.ndarray, agent_facing_xz: np.ndarray,
                 user_xz: np.ndarray, fps: float, every: int = 15, title: str = "") -> Path:
    """Top view: agent (yellow -> red) and user (blue -> green) floor trajectories coloured by
    time, the agent's facing direction as a short line every ``every`` frames.

    agent_xz, user_xz (T, 2) floor (x, z); agent_facing_xz (T, 2) facing directions (any length).
    """
    path = Path(path)
    agent_xz, user_xz = np.asarray(agent_xz, float), np.asarray(user_xz, float)
    facing = np.asarray(agent_facing_xz, float)
    facing = facing / np.maximum(np.linalg.norm(facing, axis=-1, keepdims=True), 1e-9)
    fig, ax = plt.subplots(figsize=(6, 6))
    if len(agent_xz) > 1:
        _time_line(ax, agent_xz, "autumn_r")
        _time_line(ax, user_xz, "winter")
    ticks = np.arange(0, len(agent_xz), max(1, every))
    starts, ends = agent_xz[ticks], agent_xz[ticks] + FACING_LENGTH * facing[ticks]
    tick_colours = plt.get_cmap("autumn_r")(ticks / max(1, len(agent_xz) - 1))
    ax.add_collection(LineCollection(np.stack([starts, ends], 1), colors=tick_colours,
                                     linewidths=1.2, zorder=1))
    everything = np.concatenate([agent_xz, user_xz, ends])
    low, high = everything.min(0), everything.max(0)
    centre, half = (low + high) / 2, max(float((high - low).max()) / 2 + 0.3, 0.5)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.grid(alpha=0.3)
    seconds = len(agent_xz) / fps
    ax.set_title(title or f"top view, {seconds:.1f} s")
    ax.plot([], [], color=plt.get_cmap("autumn_r")(0.6), lw=2.5, label="agent (yellow -> red)")
    ax.plot([], [], color=plt.get_cmap("winter")(0.5), lw=2.5, label="user (blue -> green)")
    ax.legend(loc="upper right", fontsize=8)
    return save_figure(fig, path)


def animate_skeleton(path: str | Path, joints: np.ndarray, parents: Sequence[int],
                     user_xz: np.ndarray, agent_speaking: np.ndarray, user_speaking: np.ndarray,
                     fps: float, frame_step: int = 3) -> Path:
    """GIF of the agent's skeleton (joints (T, J, 3), bones to ``parents``) and the user's head
    (floor position user_xz (T, 2)), with 'speaking' marks from the per-frame labels.
    Every ``frame_step``-th frame is drawn, played at fps / frame_step."""
    path = Path(path)
    joints, user_xz = np.asarray(joints, float), np.asarray(user_xz, float)
    bones = [(j, p) for j, p in enumerate(parents) if p >= 0]
    frames = np.arange(0, len(joints), max(1, frame_step))
    fig = plt.figure(figsize=(6, 5))
    ax = fig.add_subplot(projection="3d")
    # Plot axes (x, z, y): matplotlib's vertical axis is its third one.
    floor = np.concatenate([joints[..., [0, 2]].reshape(-1, 2), user_xz])
    low, high = floor.min(0), floor.max(0)
    centre, half = (low + high) / 2, max(float((high - low).max()) / 2, 1.0)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    height = max(2.2, float(joints[..., 1].max()) + 0.2)
    ax.set_zlim(0, height)
    ax.set_box_aspect((2 * half, 2 * half, height))  # metres look the same along every axis
    ax.set_xlabel("x")
    ax.set_ylabel("z")
    ax.set_zlabel("y")
    ax.view_init(elev=15, azim=-60)
    lines = [ax.plot([], [], [], color="tab:red", lw=1.5)[0] for _ in bones]
    user_head, = ax.plot([], [], [], "o", color="tab:blue", ms=10)
    user_pole, = ax.plot([], [], [], color="tab:blue", lw=1, alpha=0.5)
    agent_text = ax.text2D(0.02, 0.95, "", transform=ax.transAxes, color="tab:red")
    user_text = ax.text2D(0.02, 0.90, "", transform=ax.transAxes, color="tab:blue")
    time_text = ax.text2D(0.75, 0.95, "", transform=ax.transAxes)

    def draw(t: int):
        pose = joints[t]
        for line, (j, p) in zip(lines, bones):
            line.set_data_3d([pose[j, 0], pose[p, 0]], [pose[j, 2], pose[p, 2]],
                             [pose[j, 1], pose[p, 1]])
        ux, uz = user_xz[t]
        user_head.set_data_3d([ux], [uz], [USER_HEAD_HEIGHT])
        user_pole.set_data_3d([ux, ux], [uz, uz], [0.0, USER_HEAD_HEIGHT])
        agent_text.set_text("agent: speaking" if agent_speaking[t] else "agent")
        user_text.set_text("user: speaking" if user_speaking[t] else "user")
        time_text.set_text(f"{t / fps:5.2f} s")
        return [*lines, user_head, user_pole, agent_text, user_text, time_text]

    animation = FuncAnimation(fig, draw, frames=frames, blit=False)
    try:
        with atomic_path(path) as tmp:
            animation.save(tmp, writer=PillowWriter(fps=max(1.0, fps / max(1, frame_step))), dpi=80)
    finally:
        plt.close(fig)
    return Path(path)
