"""A generated demo dance library: rhythmic moves at known tempos, bars and rhythm signatures.

The project's own fixture and the motion source of the embedded default when the shared mocap
is absent. Every clip is built bar by bar: each bar gets a rhythm signature from ChoreoMaster's
13 common ones, and the body holds a key pose on every accented half-beat slot of it, easing
in and out between keys (zero velocity at each key). So the kinematic beats of a clip are
exactly its accented slots, and the manifest's beat, bar and signature annotations are exact.

Skeleton: 21 joints in metres, Y up, facing +Z, left side at +X, Mixamo/CMU-style names
(Hips, Spine, Chest, Neck, Head, LeftShoulder, LeftArm, LeftForeArm, LeftHand, ..., LeftUpLeg,
LeftLeg, LeftFoot, LeftToeBase, ...). The feet stay on the floor: the root height follows the
lowest toe, and planted feet are locked by ``contacts.clean_foot_skate``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import soundfile as sf
from scipy.spatial.transform import Rotation

from dancegraph.motion import quat
from dancegraph.motion.bvh import write_bvh
from dancegraph.motion.fk import canonical_positions, fk_arrays
from dancegraph.motion.skeleton import Motion, Skeleton
from dancegraph.rhythm.signatures import to_bits

DEMO_FPS = 60.0
HIPS_HEIGHT_M = 0.94
_ROOT_CHANNELS = ("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation")
_CHANNELS = ("Zrotation", "Xrotation", "Yrotation")

# (name, parent, offset in metres)
_JOINTS: tuple[tuple[str, str | None, tuple[float, float, float]], ...] = (
    ("Hips", None, (0.0, HIPS_HEIGHT_M, 0.0)),
    ("Spine", "Hips", (0.0, 0.10, 0.0)),
    ("Chest", "Spine", (0.0, 0.15, 0.0)),
    ("Neck", "Chest", (0.0, 0.20, 0.0)),
    ("Head", "Neck", (0.0, 0.10, 0.0)),
    ("LeftShoulder", "Chest", (0.04, 0.15, 0.0)),
    ("LeftArm", "LeftShoulder", (0.13, 0.0, 0.0)),
    ("LeftForeArm", "LeftArm", (0.27, 0.0, 0.0)),
    ("LeftHand", "LeftForeArm", (0.25, 0.0, 0.0)),
    ("RightShoulder", "Chest", (-0.04, 0.15, 0.0)),
    ("RightArm", "RightShoulder", (-0.13, 0.0, 0.0)),
    ("RightForeArm", "RightArm", (-0.27, 0.0, 0.0)),
    ("RightHand", "RightForeArm", (-0.25, 0.0, 0.0)),
    ("LeftUpLeg", "Hips", (0.09, -0.05, 0.0)),
    ("LeftLeg", "LeftUpLeg", (0.0, -0.42, 0.0)),
    ("LeftFoot", "LeftLeg", (0.0, -0.41, 0.0)),
    ("LeftToeBase", "LeftFoot", (0.0, -0.06, 0.12)),
    ("RightUpLeg", "Hips", (-0.09, -0.05, 0.0)),
    ("RightLeg", "RightUpLeg", (0.0, -0.42, 0.0)),
    ("RightFoot", "RightLeg", (0.0, -0.41, 0.0)),
    ("RightToeBase", "RightFoot", (0.0, -0.06, 0.12)),
)
_END_SITES = {
    "Head": (0.0, 0.15, 0.0),
    "LeftHand": (0.08, 0.0, 0.0),
    "RightHand": (-0.08, 0.0, 0.0),
    "LeftToeBase": (0.0, 0.0, 0.05),
    "RightToeBase": (0.0, 0.0, 0.05),
}


def demo_skeleton() -> Skeleton:
    """The standard demo skeleton (21 joints, metres, Y up, facing +Z)."""
    names = [n for n, _, _ in _JOINTS]
    parents = [-1 if p is None else names.index(p) for _, p, _ in _JOINTS]
    offsets = np.array([o for _, _, o in _JOINTS])
    offsets[0] = 0.0  # the root's position comes from its channels
    channels: list[tuple[str, ...]] = [_ROOT_CHANNELS] + [_CHANNELS] * (len(names) - 1)
    end_sites = {names.index(n): np.array(o) for n, o in _END_SITES.items()}
    return Skeleton(names, np.array(parents), offsets, channels, end_sites)


@dataclass(frozen=True)
class DemoClip:
    """Recipe of one demo clip."""

    id: str
    style: str
    tempo_bpm: float
    n_bars: int
    signatures: tuple[str, ...]  # one per bar, cycled


#: The library: three styles, each at two tempos, with the signature patterns its moves follow.
DEMO_CLIPS: tuple[DemoClip, ...] = (
    DemoClip("groove_100", "groove", 100.0, 8, ("00010001", "01010101", "00010101", "01010101")),
    DemoClip("groove_120", "groove", 120.0, 8, ("01010101", "00010101", "01010111", "01010101")),
    DemoClip("pop_90", "pop", 90.0, 8, ("01110111", "01010101", "01111111", "00010101")),
    DemoClip("pop_120", "pop", 120.0, 8, ("00000101", "01000101", "00000101", "01010001")),
    DemoClip("step_100", "step", 100.0, 8, ("00010001", "00000001", "00010001", "01000001")),
    DemoClip("step_120", "step", 120.0, 8, ("00010101", "00010001", "01010101", "00010001")),
)

# Euler ranges (degrees, Z X Y as in the channels) per style and joint: the pose space.
_ARMS_DOWN = {"LeftArm": (-75.0, 0.0, 0.0), "RightArm": (75.0, 0.0, 0.0)}
_STYLE_RANGES: dict[str, dict[str, tuple[tuple[float, float], ...]]] = {
    # groove: torso sway, swinging arms, soft knees
    "groove": {
        "Spine": ((-8, 8), (-5, 10), (-15, 15)),
        "Chest": ((-8, 8), (-5, 10), (-15, 15)),
        "Head": ((-10, 10), (-10, 15), (-20, 20)),
        "LeftArm": ((-40, 20), (-50, 50), (-20, 20)),
        "RightArm": ((-20, 40), (-50, 50), (-20, 20)),
        "LeftForeArm": ((0, 0), (0, 0), (-90, -10)),
        "RightForeArm": ((0, 0), (0, 0), (10, 90)),
        "knees": ((0, 0), (5, 30), (0, 0)),
    },
    # pop: sharp arm poses high and wide, head hits, straight torso
    "pop": {
        "Spine": ((-4, 4), (-4, 4), (-10, 10)),
        "Chest": ((-6, 6), (-6, 6), (-25, 25)),
        "Head": ((-20, 20), (-20, 20), (-35, 35)),
        "LeftArm": ((-60, 80), (-70, 70), (-40, 40)),
        "RightArm": ((-80, 60), (-70, 70), (-40, 40)),
        "LeftForeArm": ((0, 0), (0, 0), (-130, 0)),
        "RightForeArm": ((0, 0), (0, 0), (0, 130)),
        "knees": ((0, 0), (0, 20), (0, 0)),
    },
    # step: side steps with weight shifts; arms follow loosely
    "step": {
        "Spine": ((-10, 10), (-3, 8), (-10, 10)),
        "Chest": ((-6, 6), (-3, 6), (-10, 10)),
        "Head": ((-8, 8), (-8, 8), (-15, 15)),
        "LeftArm": ((-30, 10), (-30, 30), (-10, 10)),
        "RightArm": ((-10, 30), (-30, 30), (-10, 10)),
        "LeftForeArm": ((0, 0), (0, 0), (-60, -10)),
        "RightForeArm": ((0, 0), (0, 0), (10, 60)),
        "knees": ((0, 0), (10, 35), (0, 0)),
    },
}


def _key_pose(style: str, rng: np.random.Generator, index: int, names: list[str]) -> np.ndarray:
    """``(J, 3)`` Euler angles (deg, Z X Y) of one key pose; keys alternate sides for contrast."""
    ranges = _STYLE_RANGES[style]
    angles = np.zeros((len(names), 3))
    side = 1.0 if index % 2 == 0 else -1.0
    for joint, rng_xyz in ranges.items():
        if joint == "knees":
            continue
        lo = np.array([r[0] for r in rng_xyz])
        hi = np.array([r[1] for r in rng_xyz])
        u = rng.uniform(0.0, 1.0, 3)
        # alternate halves of the range so consecutive keys differ visibly
        u = 0.5 * u + (0.5 if side > 0 else 0.0)
        base = np.array(_ARMS_DOWN.get(joint, (0.0, 0.0, 0.0)))
        angles[names.index(joint)] = base + lo + u * (hi - lo)
    knee_lo, knee_hi = ranges["knees"][1]
    bend = knee_lo + rng.uniform(0.0, 1.0, 2) * (knee_hi - knee_lo)
    if index % 2:
        bend = bend[::-1]
    for leg, b in zip(("Left", "Right"), bend, strict=True):
        # hip flexes forward, knee back, ankle compensates: the foot stays roughly flat
        angles[names.index(f"{leg}UpLeg"), 1] = -0.5 * b
        angles[names.index(f"{leg}Leg"), 1] = b
        angles[names.index(f"{leg}Foot"), 1] = -0.5 * b
    if style == "step":
        # weight on one leg: hips roll toward it
        angles[0, 0] = side * rng.uniform(2.0, 6.0)
    angles[0, 2] = rng.uniform(-15.0, 15.0)  # the whole body turns a little
    return angles


def _ease(u: np.ndarray) -> np.ndarray:
    """Smootherstep: zero velocity and acceleration at both ends of a move, so the pause sits
    exactly on the key even next to a much faster move."""
    return u * u * u * (u * (6.0 * u - 15.0) + 10.0)


def make_clip(
    recipe: DemoClip, rng: np.random.Generator, fps: float = DEMO_FPS
) -> tuple[Motion, list[list[float]], list[str]]:
    """Generate one clip: the motion, its bars (4 beats + next downbeat, s) and signatures."""
    sk = demo_skeleton()
    beat_s = 60.0 / recipe.tempo_bpm
    bar_s = 4.0 * beat_s
    n_frames = int(round(recipe.n_bars * bar_s * fps)) + 1
    key_times: list[float] = []
    signatures: list[str] = []
    bars: list[list[float]] = []
    for b in range(recipe.n_bars):
        sig = recipe.signatures[b % len(recipe.signatures)]
        signatures.append(sig)
        start = b * bar_s
        bars.append([round(start + k * beat_s, 6) for k in range(5)])
        bits = to_bits(sig)
        key_times.extend(start + slot * beat_s / 2.0 for slot in np.flatnonzero(bits))
    key_times.append(recipe.n_bars * bar_s)
    key_times_arr = np.array(key_times)
    key_euler = np.stack(
        [_key_pose(recipe.style, rng, k, sk.names) for k in range(len(key_times_arr))]
    )
    key_quats = Rotation.from_euler("ZXY", key_euler.reshape(-1, 3), degrees=True).as_quat()
    key_quats = key_quats.reshape(len(key_times_arr), sk.n_joints, 4)
    # side steps: the hips travel between keys (metres), other styles stay near the spot
    step = 0.03 if recipe.style == "step" else 0.015
    key_x = (
        step
        * np.where(np.arange(len(key_times_arr)) % 2 == 0, 1.0, -1.0)
        * rng.uniform(0.5, 1.0, len(key_times_arr))
    )

    t = np.arange(n_frames) / fps
    seg = np.clip(np.searchsorted(key_times_arr, t, side="right") - 1, 0, len(key_times_arr) - 2)
    u = _ease(
        np.clip((t - key_times_arr[seg]) / (key_times_arr[seg + 1] - key_times_arr[seg]), 0.0, 1.0)
    )
    rotations = quat.slerp(key_quats[seg], key_quats[seg + 1], u[:, None] * np.ones(sk.n_joints))
    root = np.zeros((n_frames, 3))
    root[:, 0] = key_x[seg] + u * (key_x[seg + 1] - key_x[seg])
    root[:, 1] = HIPS_HEIGHT_M
    # keep the lowest toe on the floor
    pos, world = fk_arrays(sk, root, rotations)
    feet = canonical_positions(
        sk, pos, world, ["left_toe", "right_toe", "left_ankle", "right_ankle"]
    )
    lowest = np.minimum(feet[:, :2, 1].min(axis=1), feet[:, 2:, 1].min(axis=1) - 0.06)
    root[:, 1] -= lowest
    return Motion(sk, fps, root, rotations), bars, signatures


def library_recipes(n_takes: int | None = None) -> tuple[DemoClip, ...]:
    """The takes of a demo library: ``DEMO_CLIPS``, or ``n_takes`` cycling their styles, tempos
    and signature patterns (ids ``<recipe id>_<k>``, k from 0)."""
    if n_takes is None:
        return DEMO_CLIPS
    return tuple(
        DemoClip(f"{r.id}_{k:02d}", r.style, r.tempo_bpm, r.n_bars, r.signatures)
        for k in range(n_takes)
        for r in (DEMO_CLIPS[k % len(DEMO_CLIPS)],)
    )


#: Bars of music before a take starts (the tracker's lead-in) and after it ends.
MUSIC_LEAD_BARS = 2
MUSIC_TAIL_BARS = 1


def take_music(recipe: DemoClip, seed: int):
    """The music a demo take is danced to: a generated song (``music.generator``) at the
    take's tempo in 4/4 without drift, swing, pickup or breaks, ``MUSIC_LEAD_BARS`` bars
    before the take and ``MUSIC_TAIL_BARS`` after. Returns ``(song, offset_s)``: the song and
    the audio time (s) of the take's first frame (its first downbeat)."""
    from dancegraph.music.generator import generate, random_config

    lead, rest = MUSIC_LEAD_BARS, recipe.n_bars + MUSIC_TAIL_BARS
    cfg = random_config(
        seed,
        meter=4,
        tempo_bpm=recipe.tempo_bpm,
        form=["intro", "A", "B"],
        section_bars={"intro": lead, "A": rest // 2, "B": rest - rest // 2},
    )
    cfg.swing, cfg.drift, cfg.pickup_beats, cfg.breaks = 0.0, 0.0, 0, False
    song = generate(cfg)
    return song, float(song.truth["downbeats"][lead])


def _music_truth(song, offset_s: float, recipe: DemoClip) -> dict:
    """The take's true grid on its own clock (s): the song's beats and downbeats less the
    offset, over the take's bars."""
    span = recipe.n_bars * 4 * 60.0 / recipe.tempo_bpm + 1e-6
    beats = np.asarray(song.truth["beats"]) - offset_s
    downs = np.asarray(song.truth["downbeats"]) - offset_s
    return {
        "tempo_bpm": recipe.tempo_bpm,
        "audio_offset_s": round(offset_s, 6),
        "beats": [round(float(t), 6) for t in beats[(beats > -1e-6) & (beats <= span)]],
        "downbeats": [round(float(t), 6) for t in downs[(downs > -1e-6) & (downs <= span)]],
    }


def write_demo_library(
    out_dir: str | Path, seed: int = 0, *, n_takes: int | None = None, with_music: bool = False
) -> Path:
    """Write the demo library into ``out_dir``: one BVH per take and ``manifest.json``.

    ``n_takes``: that many takes cycling the demo recipes (default: the 6 of ``DEMO_CLIPS``).
    Without music the manifest (the format ``dancegraph dataset import`` reads) carries each
    take's style, its bars (4 beat times + the next downbeat, seconds) and each bar's rhythm
    signature. ``with_music``: each take also gets the music it is danced to
    (``<id>.ogg``, :func:`take_music`), named in the manifest with its ``audio_offset_s`` and
    no annotations (the import grids it from the music), and ``truth.json`` holds each take's
    true grid (``tempo_bpm``, ``audio_offset_s``, ``beats``, ``downbeats``, s on the take's
    clock). Returns ``out_dir``. The same arguments write the same files.
    """
    from dancegraph.motion.contacts import clean_foot_skate

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    recipes = library_recipes(n_takes)
    clips: dict[str, dict] = {}
    truth: dict[str, dict] = {}
    for k, recipe in enumerate(recipes):
        motion, bars, signatures = make_clip(recipe, rng)
        motion, _ = clean_foot_skate(motion)
        write_bvh(motion, out / f"{recipe.id}.bvh")
        clips[recipe.id] = {"file": f"{recipe.id}.bvh", "style": recipe.style}
        if with_music:
            song, offset = take_music(recipe, seed * 1000 + k)
            sf.write(out / f"{recipe.id}.ogg", song.y, song.sr, format="OGG", subtype="VORBIS")
            clips[recipe.id].update(audio=f"{recipe.id}.ogg", audio_offset_s=round(offset, 6))
            truth[recipe.id] = _music_truth(song, offset, recipe)
        else:
            clips[recipe.id].update(tempo_bpm=recipe.tempo_bpm, bars=bars, signatures=signatures)
    manifest = {
        "name": "demo",
        "licence": "generated by DanceGraph; free to use",
        "source": "dancegraph.motion.demo",
        "description": (
            f"Generated demo library (seed {seed}): {len(recipes)} takes in "
            f"{len({c.style for c in recipes})} styles at known tempos; "
            + (
                "each with the music it is danced to (truth.json: the true grids)."
                if with_music
                else "every bar's beats and rhythm signature are exact."
            )
        ),
        "fps": DEMO_FPS,
        "scale": 1.0,
        "clips": clips,
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    if with_music:
        (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    return out
