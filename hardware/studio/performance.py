"""The actor's performance: expression weights and head pose per frame.

Two takes, as in a capture session: ``rom`` (a FACS-style range-of-motion workout: each pose
eases in, holds and eases out) and ``speech`` (speech-like jaw and lip motion with blinks).
The head moves a little all the time (smooth, seeded). ``world_from_head`` maps head space
(``scene.face_rig``) into the studio's world.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from scene.camera import Rigid
from scene.face_rig import FaceRig, load_face_rig

# FACS-style poses of the range-of-motion take (ICT blendshape name -> weight).
ROM_POSES: tuple[tuple[str, dict[str, float]], ...] = (
    ("jaw_open", {"jawOpen": 0.7, "mouthLowerDown_L": 0.3, "mouthLowerDown_R": 0.3}),
    ("smile", {"mouthSmile_L": 0.9, "mouthSmile_R": 0.9, "cheekSquint_L": 0.5, "cheekSquint_R": 0.5}),
    ("brows_up", {"browInnerUp_L": 0.9, "browInnerUp_R": 0.9, "browOuterUp_L": 0.8, "browOuterUp_R": 0.8, "eyeWide_L": 0.4, "eyeWide_R": 0.4}),
    ("pucker", {"mouthPucker": 0.9, "mouthFunnel": 0.3}),
    ("brows_down", {"browDown_L": 0.9, "browDown_R": 0.9, "noseSneer_L": 0.4, "noseSneer_R": 0.4}),
    ("eyes_closed", {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}),
    ("stretch", {"mouthStretch_L": 0.8, "mouthStretch_R": 0.8, "jawOpen": 0.2}),
    ("jaw_left", {"jawLeft": 0.7, "mouthLeft": 0.5}),
    ("funnel", {"mouthFunnel": 0.9, "jawOpen": 0.25}),
    ("frown", {"mouthFrown_L": 0.9, "mouthFrown_R": 0.9, "mouthShrugLower": 0.5}),
    ("jaw_right", {"jawRight": 0.7, "mouthRight": 0.5}),
    ("cheek_puff", {"cheekPuff_L": 0.9, "cheekPuff_R": 0.9, "mouthClose": 0.3}),
    ("smile_left", {"mouthSmile_L": 0.9, "cheekSquint_L": 0.6, "eyeSquint_L": 0.4}),
    ("sneer", {"noseSneer_L": 0.8, "noseSneer_R": 0.8, "mouthUpperUp_L": 0.6, "mouthUpperUp_R": 0.6}),
)

# Scan session (static poses, neutral first): what a scanning booth would capture of this actor.
SCAN_POSES: tuple[tuple[str, dict[str, float]], ...] = (("neutral", {}),) + tuple(
    (name, weights) for name, weights in ROM_POSES if name in (
        "jaw_open", "smile", "brows_up", "pucker", "brows_down", "eyes_closed", "stretch", "funnel", "jaw_left"))


@dataclass(frozen=True)
class FrameState:
    """Everything about the subject at one frame.

    Attributes:
        index: global frame index (0 .. F-1 over all takes).
        take: take name (``rom`` / ``speech``).
        time_s: capture time of the frame, seconds from the first frame.
        expression_weights: [57] ICT blendshape weights.
        world_from_head: head pose.
    """

    index: int
    take: str
    time_s: float
    expression_weights: np.ndarray
    world_from_head: Rigid


def pose_weights(rig: FaceRig, pose: dict[str, float]) -> np.ndarray:
    """A [57] weight vector from a ``name -> weight`` dict."""
    w = np.zeros(rig.num_expressions, np.float32)
    for name, value in pose.items():
        w[rig.expression_index(name)] = value
    return w


def _ease(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _smooth_signal(rng: np.random.Generator, t: np.ndarray, freqs_hz: tuple[float, ...]) -> np.ndarray:
    """Sum of sinusoids with random phases and amplitudes, normalised to about [-1, 1]."""
    out = np.zeros_like(t)
    amps = rng.uniform(0.5, 1.0, len(freqs_hz))
    for f, a in zip(freqs_hz, amps):
        out += a * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return out / amps.sum()


def rom_weights(rig: FaceRig, t_take: np.ndarray, duration_s: float, pose_seconds: float, offset: int = 0) -> np.ndarray:
    """Range-of-motion weights [N, 57] at take times ``t_take``: poses in turn, eased in and out."""
    n_poses = max(1, int(duration_s // pose_seconds))
    weights = np.zeros((len(t_take), rig.num_expressions), np.float32)
    for k in range(n_poses):
        _, pose = ROM_POSES[(k + offset) % len(ROM_POSES)]
        phase = (t_take - k * pose_seconds) / pose_seconds  # 0..1 within the pose's slot
        envelope = _ease(phase / 0.35) * _ease((1.0 - phase) / 0.35) * ((phase >= 0) & (phase <= 1))
        weights += envelope[:, None] * pose_weights(rig, pose)[None]
    return weights


def speech_weights(rig: FaceRig, t_take: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Speech-like weights [N, 57]: syllabic jaw motion, lip shapes, blinks."""
    w = np.zeros((len(t_take), rig.num_expressions), np.float32)
    syllable = 0.5 + 0.5 * np.sin(2 * np.pi * 2.6 * t_take + rng.uniform(0, 6.3))
    loud = 0.5 + 0.5 * _smooth_signal(rng, t_take, (0.3, 0.7))
    w[:, rig.expression_index("jawOpen")] = 0.05 + 0.35 * syllable * loud
    for name, freqs in (("mouthFunnel", (0.9, 1.7)), ("mouthPucker", (0.6, 1.3)),
                        ("mouthSmile_L", (0.2, 0.5)), ("mouthSmile_R", (0.2, 0.5)),
                        ("mouthLowerDown_L", (1.1, 2.1)), ("mouthLowerDown_R", (1.1, 2.1)),
                        ("mouthUpperUp_L", (0.8, 1.9)), ("mouthUpperUp_R", (0.8, 1.9)),
                        ("browInnerUp_L", (0.25, 0.45)), ("browInnerUp_R", (0.25, 0.45))):
        w[:, rig.expression_index(name)] = 0.35 * np.clip(_smooth_signal(rng, t_take, freqs), 0, None)
    blink_times = np.arange(rng.uniform(0.3, 1.0), t_take.max() + 1.0, rng.uniform(1.8, 2.8))
    blink = np.zeros_like(t_take)
    for tb in blink_times:
        blink = np.maximum(blink, np.exp(-0.5 * ((t_take - tb) / 0.06) ** 2))
    w[:, rig.expression_index("eyeBlink_L")] = blink
    w[:, rig.expression_index("eyeBlink_R")] = blink
    return w


def head_motion(t: np.ndarray, rng: np.random.Generator, head_center_world: np.ndarray,
                rotation_deg: float = 4.0, translation_m: float = 0.008) -> list[Rigid]:
    """Small, smooth head motion: ``world_from_head`` per time, rotating about the neck."""
    from scipy.spatial.transform import Rotation

    yaw = np.radians(rotation_deg) * _smooth_signal(rng, t, (0.11, 0.23, 0.41))
    pitch = np.radians(0.7 * rotation_deg) * _smooth_signal(rng, t, (0.13, 0.29, 0.37))
    roll = np.radians(0.4 * rotation_deg) * _smooth_signal(rng, t, (0.09, 0.31))
    trans = translation_m * np.stack([_smooth_signal(rng, t, (0.07, 0.19)), _smooth_signal(rng, t, (0.05, 0.17)),
                                      _smooth_signal(rng, t, (0.06, 0.21))], -1)
    pivot = np.array([0.0, -0.08, -0.02])  # rotate about the top of the neck (head space), not the nose
    poses = []
    for i in range(len(t)):
        R = Rotation.from_euler("yxz", [yaw[i], pitch[i], roll[i]]).as_matrix()
        translation = head_center_world + trans[i] + pivot - R @ pivot
        poses.append(Rigid(R, translation))
    return poses


def make_performance(seed: int, takes: tuple[str, ...] = ("rom", "speech"), frames_per_take: int | Sequence[int] = 48,
                     fps: float = 24.0, rom_pose_seconds: float = 0.6,
                     head_center_world: np.ndarray | None = None, rig: FaceRig | None = None,
                     head_motion_deg: float = 4.0) -> list[FrameState]:
    """The frames of a capture session, deterministic in ``seed``.

    Args:
        takes: take names in order; ``rom`` and ``speech`` are known.
        frames_per_take: frames in each take (one count for all, or one per take); a
            multiple of the OLAT pattern cycle (48 frames for 32 bars) keeps takes aligned.
        fps: frame rate; frames are ``1/fps`` apart and takes follow each other without a gap.
        rom_pose_seconds: time for one range-of-motion pose (ease in, hold, ease out).
        head_center_world: [3] where the head stands (``RigConfig.head_center_m``).
        head_motion_deg: amplitude of the head's yaw (pitch and roll are smaller); 0 = still.
    """
    rig = rig or load_face_rig()
    rng = np.random.default_rng(np.random.SeedSequence([0xFACE, int(seed)]))
    centre = np.zeros(3) if head_center_world is None else np.asarray(head_center_world, float)
    counts = [int(frames_per_take)] * len(takes) if isinstance(frames_per_take, (int, np.integer)) \
        else [int(c) for c in frames_per_take]
    if len(counts) != len(takes) or min(counts, default=0) < 0:
        raise ValueError(f"frames_per_take {frames_per_take!r} does not give a count >= 0 for each take {takes}")
    n_total = sum(counts)
    t_all = np.arange(n_total) / fps
    poses = head_motion(t_all, rng, centre, rotation_deg=head_motion_deg,
                        translation_m=0.002 * head_motion_deg)
    frames: list[FrameState] = []
    start = 0
    for take, count in zip(takes, counts):
        if count == 0:
            continue
        t_take = np.arange(count) / fps
        if take == "rom":
            weights = rom_weights(rig, t_take, count / fps, rom_pose_seconds, offset=int(rng.integers(len(ROM_POSES))))
        elif take == "speech":
            weights = speech_weights(rig, t_take, rng)
        else:
            raise ValueError(f"unknown take '{take}'; known takes: rom, speech")
        for i in range(count):
            g = start + i
            frames.append(FrameState(g, take, float(t_all[g]), weights[i], poses[g]))
        start += count
    return frames
