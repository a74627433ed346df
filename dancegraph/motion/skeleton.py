"""Skeletons and motions: the explicit joint hierarchy and per-frame joint rotations.

Units are metres and seconds; quaternions are scipy's ``(x, y, z, w)``. Y is up. A skeleton is
an explicit object (names, parents, offsets, BVH channel layout, end sites, and a map from
canonical joint names to its own names) so that nothing depends on array positions alone.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

#: Canonical joint names every skeleton is mapped onto (``Skeleton.canonical`` keys).
CANONICAL_JOINTS: tuple[str, ...] = (
    "hips",
    "spine",
    "chest",
    "neck",
    "head",
    "left_shoulder",
    "left_elbow",
    "left_wrist",
    "right_shoulder",
    "right_elbow",
    "right_wrist",
    "left_hip",
    "left_knee",
    "left_ankle",
    "left_toe",
    "right_hip",
    "right_knee",
    "right_ankle",
    "right_toe",
)

# Candidate joint names (lower case, tried in order) per canonical joint; "{s}" is a side token.
# "shoulder" means the upper-arm joint (the shoulder's ball joint), not the clavicle.
_CANDIDATES: dict[str, tuple[str, ...]] = {
    "hips": ("hips", "hip", "pelvis", "root"),
    "spine": ("abdomen", "spine", "lowerback", "spine0"),
    "chest": ("chest", "spine1", "spine2", "upperchest", "thorax"),
    "neck": ("neck", "neck1"),
    "head": ("head",),
    "shoulder": ("{s}shldr", "{s}arm", "{s}upperarm", "{s}shoulder_ball", "upperarm_{s}"),
    "elbow": ("{s}forearm", "{s}lowerarm", "{s}elbow", "lowerarm_{s}"),
    "wrist": ("{s}hand", "{s}wrist", "hand_{s}"),
    "hip": ("{s}thigh", "{s}upleg", "{s}upperleg", "{s}hip", "thigh_{s}"),
    "knee": ("{s}shin", "{s}leg", "{s}lowerleg", "{s}knee", "calf_{s}"),
    "ankle": ("{s}foot", "{s}ankle", "foot_{s}"),
    "toe": ("{s}toebase", "{s}toe", "{s}toes", "toe_{s}", "ball_{s}"),
}
_SIDE_TOKENS = {"left": ("left", "l"), "right": ("right", "r")}


def find_canonical(names: list[str]) -> dict[str, str]:
    """Map canonical joint names to joint names by common naming schemes (CMU, Daz, Mixamo).

    Returns only the canonical joints that were found. A skeleton without toe joints maps
    ``*_toe`` to the ankle joint; ``fk.canonical_positions`` then uses the ankle's end site.
    """
    lower = {n.lower(): n for n in names}
    found: dict[str, str] = {}
    for key in CANONICAL_JOINTS:
        if key.startswith(("left_", "right_")):
            side, part = key.split("_", 1)
            cands = [c.format(s=tok) for c in _CANDIDATES[part] for tok in _SIDE_TOKENS[side]]
        else:
            cands = list(_CANDIDATES[key])
        for cand in cands:
            if cand in lower:
                found[key] = lower[cand]
                break
    for side in ("left", "right"):
        if f"{side}_toe" not in found and f"{side}_ankle" in found:
            found[f"{side}_toe"] = found[f"{side}_ankle"]
    return found


# (left pattern, left token, right pattern, right token): how a name's side is written.
_SIDE_SWAPS: tuple[tuple[str, str, str, str], ...] = (
    (r"^Left(?=[A-Z_0-9])", "Left", r"^Right(?=[A-Z_0-9])", "Right"),
    (r"^left(?=[A-Z_0-9])", "left", r"^right(?=[A-Z_0-9])", "right"),
    (r"^L(?=[A-Z_])", "L", r"^R(?=[A-Z_])", "R"),
    (r"^l(?=[A-Z_])", "l", r"^r(?=[A-Z_])", "r"),
    (r"_l$", "_l", r"_r$", "_r"),
    (r"_L$", "_L", r"_R$", "_R"),
    (r"\.L$", ".L", r"\.R$", ".R"),
)


def find_mirror_pairs(names: list[str]) -> list[tuple[int, int]]:
    """Left/right joint index pairs ``(left, right)`` found from name prefixes/suffixes.

    Recognised: ``l``/``r`` before a capital (lShldr/rShldr), ``L``/``R`` (LHipJoint/RHipJoint),
    ``Left``/``Right`` and ``left``/``right`` prefixes, and ``_l``/``_r``, ``.L``/``.R`` suffixes.
    """
    index = {n: i for i, n in enumerate(names)}
    pairs: list[tuple[int, int]] = []
    paired: set[int] = set()
    for i, name in enumerate(names):
        if i in paired:
            continue
        for left_pat, _left_tok, _right_pat, right_tok in _SIDE_SWAPS:
            if re.search(left_pat, name):
                other = re.sub(left_pat, right_tok, name)
                j = index.get(other)
                if j is not None and j not in paired:
                    pairs.append((i, j))
                    paired.update((i, j))
                    break
    return sorted(pairs)


@dataclass
class Skeleton:
    """A joint hierarchy in BVH terms.

    - ``names``: J joint names, parents before children (BVH order).
    - ``parents``: ``(J,)`` int, -1 for the root.
    - ``offsets``: ``(J, 3)`` metres, each joint's position in its parent's frame at rest.
    - ``channels``: per joint, BVH channel names in file order (the root has 6, others 3 or 0).
    - ``end_sites``: joint index → ``(3,)`` metres, the End Site offset below that joint.
    - ``canonical``: canonical joint name (see ``CANONICAL_JOINTS``) → this skeleton's joint name.
    """

    names: list[str]
    parents: np.ndarray
    offsets: np.ndarray
    channels: list[tuple[str, ...]]
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)
    canonical: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.parents = np.asarray(self.parents, dtype=np.int64)
        self.offsets = np.asarray(self.offsets, dtype=float).reshape(-1, 3)
        self.channels = [tuple(c) for c in self.channels]
        self.end_sites = {int(k): np.asarray(v, dtype=float) for k, v in self.end_sites.items()}
        if not self.canonical:
            self.canonical = find_canonical(self.names)
        self._index = {n: i for i, n in enumerate(self.names)}

    @property
    def n_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        """Joint index of ``name`` (a joint name or a canonical name); KeyError if absent."""
        if name in self._index:
            return self._index[name]
        if name in self.canonical:
            return self._index[self.canonical[name]]
        raise KeyError(f"no joint {name!r} in skeleton")

    def mirror_pairs(self) -> list[tuple[int, int]]:
        """Left/right joint index pairs found from the joint names."""
        return find_mirror_pairs(self.names)

    def children(self, joint: int) -> list[int]:
        return [int(i) for i in np.flatnonzero(self.parents == joint)]

    def to_dict(self) -> dict:
        """JSON-able form (lists and floats)."""
        return {
            "names": list(self.names),
            "parents": [int(p) for p in self.parents],
            "offsets": self.offsets.tolist(),
            "channels": [list(c) for c in self.channels],
            "end_sites": {str(k): v.tolist() for k, v in sorted(self.end_sites.items())},
            "canonical": dict(self.canonical),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Skeleton:
        return cls(
            names=list(d["names"]),
            parents=np.asarray(d["parents"], dtype=np.int64),
            offsets=np.asarray(d["offsets"], dtype=float),
            channels=[tuple(c) for c in d["channels"]],
            end_sites={
                int(k): np.asarray(v, dtype=float) for k, v in d.get("end_sites", {}).items()
            },
            canonical=dict(d.get("canonical", {})),
        )

    def __eq__(self, other: object) -> bool:
        """Same hierarchy and channels, offsets equal to BVH printed precision (1e-6 m)."""
        if not isinstance(other, Skeleton):
            return NotImplemented
        return (
            self.names == other.names
            and np.array_equal(self.parents, other.parents)
            and np.allclose(self.offsets, other.offsets, rtol=0, atol=1e-6)
            and self.channels == other.channels
            and sorted(self.end_sites) == sorted(other.end_sites)
            and all(
                np.allclose(self.end_sites[k], other.end_sites[k], rtol=0, atol=1e-6)
                for k in self.end_sites
            )
        )


@dataclass
class Motion:
    """Animation of a skeleton.

    - ``fps``: frames per second.
    - ``root_positions``: ``(F, 3)`` metres, the root joint's position per frame.
    - ``rotations``: ``(F, J, 4)`` local joint rotations (x, y, z, w) relative to the parent.
    """

    skeleton: Skeleton
    fps: float
    root_positions: np.ndarray
    rotations: np.ndarray

    def __post_init__(self) -> None:
        self.fps = float(self.fps)
        self.root_positions = np.asarray(self.root_positions, dtype=float)
        self.rotations = np.asarray(self.rotations, dtype=float)
        f, j = self.rotations.shape[:2]
        if self.rotations.shape != (f, self.skeleton.n_joints, 4):
            raise ValueError(
                f"rotations shape {self.rotations.shape} does not fit "
                f"{self.skeleton.n_joints} joints"
            )
        if self.root_positions.shape != (f, 3):
            raise ValueError(f"root_positions shape {self.root_positions.shape} != ({f}, 3)")

    @property
    def n_frames(self) -> int:
        return int(self.rotations.shape[0])

    @property
    def duration_s(self) -> float:
        """Frames × frame time (a half-open span: the last frame lasts one frame time)."""
        return self.n_frames / self.fps

    def slice(self, start: int, stop: int) -> Motion:
        """Frames ``[start, stop)`` as a new motion (copies)."""
        return Motion(
            self.skeleton,
            self.fps,
            self.root_positions[start:stop].copy(),
            self.rotations[start:stop].copy(),
        )

    def copy(self) -> Motion:
        return Motion(self.skeleton, self.fps, self.root_positions.copy(), self.rotations.copy())
