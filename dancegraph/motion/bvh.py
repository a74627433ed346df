"""BVH read/write for any joint count, channel layout and Euler order.

The hierarchy is parsed token by token (it is small); the motion block is parsed in one
vectorised call (``np.fromstring``), so a 100,000-frame file reads in seconds. Every defect a
user's file can have becomes a ``MotionFileError`` with a stable code, the file and, where it
applies, the 1-based line number:

``bvh_not_text``, ``bvh_syntax``, ``bvh_truncated``, ``bvh_channel_count``, ``bvh_nan``,
``bvh_no_frames``, ``bvh_rotation_order``, ``bvh_duplicate_joint``, ``bvh_frame_time``, and
``bvh_too_complex`` for a file past the reader's limits, checked before anything is allocated
for it: :data:`MAX_JOINTS` joints, :data:`MAX_DEPTH` nesting, :data:`MAX_HEADER_BYTES` of
hierarchy, and ``max_values`` frames × channels (:data:`MAX_VALUES` by default). The hierarchy is
walked with an explicit stack, so no nesting can exhaust Python's recursion limit.

Rotations: BVH Euler channels are intrinsic, applied in file order (``Zrotation Xrotation
Yrotation`` means ``R = Rz · Rx · Ry``), which is scipy's upper-case ``"ZXY"``.
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from dancegraph.errors import MotionFileError
from dancegraph.motion import quat
from dancegraph.motion.skeleton import Motion, Skeleton

_POSITION = {"Xposition": "X", "Yposition": "Y", "Zposition": "Z"}
_ROTATION = {"Xrotation": "X", "Yrotation": "Y", "Zrotation": "Z"}
_MOTION_RE = re.compile(r"^[ \t]*MOTION[ \t]*\r?$", re.MULTILINE | re.IGNORECASE)
_MOTION_BYTES_RE = re.compile(rb"^[ \t]*MOTION[ \t]*\r?$", re.MULTILINE | re.IGNORECASE)
_FLOAT_RE = re.compile(r"^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")

#: Most joints in one hierarchy (a face-rigged character has a few hundred).
MAX_JOINTS = 2000
#: Deepest joint nesting (a finger tip of a detailed rig sits about 30 deep).
MAX_DEPTH = 256
#: Largest hierarchy (the text before ``MOTION``).
MAX_HEADER_BYTES = 8 * 1024 * 1024
#: Most frames × channels :func:`read_bvh` parses by default (20 minutes at 120 fps of 115
#: joints; about 0.4 GB as float64).
MAX_VALUES = 50_000_000


def _too_complex(what: str, path: str, line: int | None = None) -> MotionFileError:
    return MotionFileError(what, path=path, line=line, code="bvh_too_complex")


class _Tokens:
    """Header tokens with their 1-based line numbers."""

    def __init__(self, lines: list[str], path: str):
        self.items: list[tuple[str, int]] = []
        for no, line in enumerate(lines, start=1):
            for tok in line.replace("{", " { ").replace("}", " } ").split():
                self.items.append((tok, no))
        self.pos = 0
        self.path = path
        self.last_line = len(lines)

    def next(self, what: str) -> tuple[str, int]:
        if self.pos >= len(self.items):
            raise MotionFileError(
                f"file ends inside the hierarchy (expected {what})",
                path=self.path,
                line=self.last_line,
                code="bvh_truncated",
            )
        tok = self.items[self.pos]
        self.pos += 1
        return tok

    def expect(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok.lower() != word.lower():
            raise MotionFileError(
                f"expected {word!r}, found {tok[:100]!r}",
                path=self.path,
                line=line,
                code="bvh_syntax",
            )
        return line

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        if not _FLOAT_RE.match(tok):
            code = "bvh_nan" if tok.lower() in {"nan", "inf", "-inf", "+inf"} else "bvh_syntax"
            raise MotionFileError(
                f"expected a number ({what}), found {tok[:100]!r}",
                path=self.path,
                line=line,
                code=code,
            )
        value = float(tok)
        if not np.isfinite(value):  # 1e999
            raise MotionFileError(
                f"{what} is not finite ({tok[:100]!r})", path=self.path, line=line, code="bvh_nan"
            )
        return value


def _check_text(raw: bytes, path: str) -> str:
    if b"\x00" in raw:
        raise MotionFileError("not a text BVH file (binary data)", path=path, code="bvh_not_text")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise MotionFileError(
            "not a text BVH file (undecodable bytes)", path=path, line=line, code="bvh_not_text"
        ) from None
    stripped = text.lstrip()
    if not stripped.upper().startswith("HIERARCHY"):
        printable = sum(c.isprintable() or c in "\r\n\t" for c in stripped[:4096])
        code = "bvh_not_text" if printable < 0.95 * max(1, len(stripped[:4096])) else "bvh_syntax"
        if not stripped:
            code = "bvh_truncated"
        raise MotionFileError(
            "not a BVH file (it must start with HIERARCHY)", path=path, line=1, code=code
        )
    return text


class _Hierarchy:
    """The joints read so far: names, parents, offsets, channels, end sites."""

    def __init__(self, path: str):
        self.path = path
        self.names: list[str] = []
        self.parents: list[int] = []
        self.offsets: list[list[float]] = []
        self.channels: list[tuple[str, ...]] = []
        self.end_sites: dict[int, np.ndarray] = {}
        self.seen: dict[str, int] = {}

    def joint(self, tokens: _Tokens, parent: int) -> int:
        """Read one joint's name, OFFSET and CHANNELS (up to its children); its index."""
        path = self.path
        name, name_line = tokens.next("a joint name")
        if name in ("{", "}"):
            raise MotionFileError(
                "joint without a name", path=path, line=name_line, code="bvh_syntax"
            )
        if name in self.seen:
            raise MotionFileError(
                f"duplicate joint name {name[:100]!r} (first on line {self.seen[name]})",
                path=path,
                line=name_line,
                code="bvh_duplicate_joint",
            )
        if len(self.names) >= MAX_JOINTS:
            raise _too_complex(f"more than {MAX_JOINTS} joints", path, name_line)
        self.seen[name] = name_line
        self.names.append(name)
        self.parents.append(parent)
        tokens.expect("{")
        tokens.expect("OFFSET")
        self.offsets.append(
            [tokens.number("OFFSET x"), tokens.number("OFFSET y"), tokens.number("OFFSET z")]
        )
        self.channels.append(_channels(tokens, name, path))
        return len(self.names) - 1

    def end_site(self, tokens: _Tokens, joint: int) -> None:
        tokens.expect("Site")
        tokens.expect("{")
        tokens.expect("OFFSET")
        self.end_sites[joint] = np.array(
            [tokens.number("OFFSET x"), tokens.number("OFFSET y"), tokens.number("OFFSET z")]
        )
        tokens.expect("}")


def _channels(tokens: _Tokens, name: str, path: str) -> tuple[str, ...]:
    """A joint's ``CHANNELS n ...`` line: position and rotation channels, each axis once."""
    tok, line = tokens.next("CHANNELS")
    if tok.upper() != "CHANNELS":
        raise MotionFileError(
            f"expected CHANNELS, found {tok[:100]!r}", path=path, line=line, code="bvh_syntax"
        )
    n_tok, n_line = tokens.next("a channel count")
    if not (n_tok.isascii() and n_tok.isdigit()):
        raise MotionFileError(
            f"expected a channel count, found {n_tok[:100]!r}",
            path=path,
            line=n_line,
            code="bvh_syntax",
        )
    chans = []
    for _ in range(min(int(n_tok), 7)):  # more than six repeats an axis: refused below
        ch, ch_line = tokens.next("a channel name")
        if ch not in _POSITION and ch not in _ROTATION:
            raise MotionFileError(
                f"unknown channel {ch[:100]!r} of joint {name[:100]!r}",
                path=path,
                line=ch_line,
                code="bvh_rotation_order",
            )
        chans.append(ch)
    rot_axes = [_ROTATION[c] for c in chans if c in _ROTATION]
    if rot_axes and sorted(rot_axes) != ["X", "Y", "Z"]:
        raise MotionFileError(
            f"joint {name[:100]!r} has rotation channels {' '.join(rot_axes)}: an Euler order "
            "needs X, Y and Z once each",
            path=path,
            line=n_line,
            code="bvh_rotation_order",
        )
    pos_axes = [_POSITION[c] for c in chans if c in _POSITION]
    if pos_axes and sorted(pos_axes) != ["X", "Y", "Z"]:
        raise MotionFileError(
            f"joint {name[:100]!r} has position channels {' '.join(pos_axes)}; X, Y and Z are "
            "needed",
            path=path,
            line=n_line,
            code="bvh_channel_count",
        )
    return tuple(chans)


def _parse_hierarchy(tokens: _Tokens, path: str):
    """``(names, parents, offsets, channels, end_sites)`` of the HIERARCHY block; the joints
    are read with an explicit stack of open joints (at most :data:`MAX_DEPTH`)."""
    tree = _Hierarchy(path)
    tokens.expect("HIERARCHY")
    tok, line = tokens.next("ROOT")
    if tok.upper() != "ROOT":
        raise MotionFileError(
            f"expected ROOT, found {tok[:100]!r}", path=path, line=line, code="bvh_syntax"
        )
    open_joints = [tree.joint(tokens, -1)]
    while open_joints:
        tok, line = tokens.next("JOINT, End Site or }")
        up = tok.upper()
        if up == "}":
            open_joints.pop()
        elif up == "JOINT":
            if len(open_joints) >= MAX_DEPTH:
                raise _too_complex(f"joints nested more than {MAX_DEPTH} deep", path, line)
            open_joints.append(tree.joint(tokens, open_joints[-1]))
        elif up == "END":
            tree.end_site(tokens, open_joints[-1])
        else:
            raise MotionFileError(
                f"expected JOINT, End Site or '}}', found {tok[:100]!r}",
                path=path,
                line=line,
                code="bvh_syntax",
            )
    if tokens.pos < len(tokens.items):
        tok, line = tokens.items[tokens.pos]
        raise MotionFileError(
            f"unexpected {tok[:100]!r} after the root joint (one ROOT per file is supported)",
            path=path,
            line=line,
            code="bvh_syntax",
        )
    return tree.names, tree.parents, tree.offsets, tree.channels, tree.end_sites


def read_bvh_skeleton(path: str | os.PathLike, *, scale: float = 1.0) -> Skeleton:
    """The hierarchy of a BVH file (a rig's), its frames left unparsed.

    Reads at most :data:`MAX_HEADER_BYTES` (plus one chunk) into memory whatever the file's
    size; the rest is only scanned for NUL bytes (``bvh_not_text``). ``scale``: metres per file
    unit. Raises ``MotionFileError`` as :func:`read_bvh` does for the hierarchy.
    """
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale}")
    pname = str(path)
    head = bytearray()
    motion = None
    try:
        with open(path, "rb") as fh:
            while chunk := fh.read(1 << 20):
                if b"\x00" in chunk:
                    raise MotionFileError(
                        "not a text BVH file (binary data)", path=pname, code="bvh_not_text"
                    )
                if motion is None:
                    head += chunk
                    motion = _MOTION_BYTES_RE.search(head)
                    if motion is None and len(head) > MAX_HEADER_BYTES:
                        raise _too_complex(f"no MOTION line in {MAX_HEADER_BYTES} bytes", pname)
    except OSError as exc:
        raise MotionFileError(
            f"cannot read: {exc.strerror}", path=pname, code="bvh_unreadable"
        ) from None
    if motion is None:
        raise MotionFileError("no MOTION section", path=pname, code="bvh_truncated")
    if motion.start() > MAX_HEADER_BYTES:
        raise _too_complex(f"a hierarchy larger than {MAX_HEADER_BYTES} bytes", pname)
    text = _check_text(bytes(head[: motion.start()]), pname)
    names, parents, offsets, channels, end_sites = _parse_hierarchy(
        _Tokens(text.split("\n"), pname), pname
    )
    return Skeleton(
        names=names,
        parents=np.asarray(parents),
        offsets=np.asarray(offsets) * scale,
        channels=channels,
        end_sites={k: v * scale for k, v in end_sites.items()},
    )


def _euler_order(chans: tuple[str, ...]) -> str:
    return "".join(_ROTATION[c] for c in chans if c in _ROTATION)


def read_bvh(
    path: str | os.PathLike,
    *,
    scale: float = 1.0,
    fps: float | None = None,
    max_values: int = MAX_VALUES,
) -> Motion:
    """Read a BVH file.

    ``scale`` converts file units to metres (0.056444 for CMU ASF units); ``fps`` overrides the
    header's frame time (e.g. 60 for CMU takes published with a 120 fps header). A frame time
    within 0.1 % of a whole frame rate is rounded to it (0.008333 s → 120 fps). Joints without
    rotation channels get identity rotations; position channels below the root are read but
    not kept (the offsets stand). A file of more than ``max_values`` frames × channels is
    refused (``bvh_too_complex``) before its frames are parsed.
    """
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale}")
    path = Path(path)
    pname = str(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise MotionFileError(
            f"cannot read: {exc.strerror}", path=pname, code="bvh_unreadable"
        ) from None
    text = _check_text(raw, pname)
    found = _MOTION_RE.search(text)
    if found is None:
        if len(text) > MAX_HEADER_BYTES:
            raise _too_complex(f"no MOTION line in the first {MAX_HEADER_BYTES} bytes", pname)
        lines = text.split("\n")
        tokens = _Tokens(lines, pname)
        try:
            _parse_hierarchy(tokens, pname)
        except MotionFileError as exc:
            # a header that breaks on its very last token was cut off, not misspelt
            if exc.code != "bvh_duplicate_joint" and tokens.pos >= len(tokens.items):
                raise MotionFileError(
                    "file ends inside the hierarchy",
                    path=pname,
                    line=exc.line,
                    code="bvh_truncated",
                ) from None
            raise
        raise MotionFileError(
            "no MOTION section", path=pname, line=len(lines), code="bvh_truncated"
        )
    # Only the header is split into lines; the frame block stays one string for numpy.
    lines = text[: found.start()].split("\n")
    motion_line = len(lines) - 1
    pos = found.end()
    for _ in range(2):
        nl = text.find("\n", pos + 1)
        nl = len(text) if nl < 0 else nl
        lines.append(text[pos + 1 : nl] if pos < len(text) else "")
        pos = nl
    lines[motion_line] = "MOTION"
    frame_block = text[pos + 1 :] if pos < len(text) else ""
    if found.start() > MAX_HEADER_BYTES:
        raise _too_complex(f"a hierarchy larger than {MAX_HEADER_BYTES} bytes", pname)
    names, parents, offsets, channels, end_sites = _parse_hierarchy(
        _Tokens(lines[:motion_line], pname), pname
    )
    n_channels = sum(len(c) for c in channels)

    def header_value(offset: int, key: str) -> tuple[str, int]:
        no = motion_line + offset
        if no >= len(lines) or not lines[no].strip():
            raise MotionFileError(
                f"missing '{key}' line", path=pname, line=no + 1, code="bvh_truncated"
            )
        line = " ".join(lines[no].split())
        if not line.lower().startswith(key.lower()):
            raise MotionFileError(
                f"expected '{key}', found {line[:40]!r}", path=pname, line=no + 1, code="bvh_syntax"
            )
        return line[len(key) :].strip(), no + 1

    frames_tok, frames_line = header_value(1, "Frames:")
    if not (frames_tok.isascii() and frames_tok.isdigit()):
        raise MotionFileError(
            f"bad frame count {frames_tok[:100]!r}", path=pname, line=frames_line, code="bvh_syntax"
        )
    n_frames = int(frames_tok)
    if n_frames * n_channels > max_values:
        raise _too_complex(
            f"{n_frames} frames of {n_channels} channels: more than {max_values} values",
            pname,
            frames_line,
        )
    if n_frames == 0:
        raise MotionFileError(
            "the file has zero frames", path=pname, line=frames_line, code="bvh_no_frames"
        )
    ft_tok, ft_line = header_value(2, "Frame Time:")
    try:
        frame_time = float(ft_tok)
    except ValueError:
        raise MotionFileError(
            f"bad frame time {ft_tok!r}", path=pname, line=ft_line, code="bvh_frame_time"
        ) from None
    if not np.isfinite(frame_time) or frame_time <= 0:
        raise MotionFileError(
            f"bad frame time {ft_tok!r}", path=pname, line=ft_line, code="bvh_frame_time"
        )

    first_data = motion_line + 3  # 0-based index of the first data line
    data = _parse_frames(frame_block, first_data, n_frames, n_channels, pname)

    skeleton = Skeleton(
        names=names,
        parents=np.asarray(parents),
        offsets=np.asarray(offsets) * scale,
        channels=channels,
        end_sites={k: v * scale for k, v in end_sites.items()},
    )
    root_positions, rotations = _channels_to_pose(data, skeleton, scale)
    if fps is None:
        fps = 1.0 / frame_time
        if abs(fps - round(fps)) < 1e-3 * fps:
            fps = float(round(fps))
    return Motion(skeleton, float(fps), root_positions, rotations)


def _parse_frames(block: str, first: int, n_frames: int, n_channels: int, path: str) -> np.ndarray:
    """The ``(n_frames, n_channels)`` data block; raise with the offending line where it breaks.

    ``block`` is the text after the ``Frame Time`` line, ``first`` its 0-based line number.
    """
    block = block.rstrip()
    values = None
    if n_channels > 0 and block:
        try:
            values = np.fromstring(block, sep=" ")
        except ValueError:
            values = None  # a token that is not a number: locate it below
    n_lines = block.count("\n") + 1 if block else 0
    if values is not None and values.size == n_frames * n_channels and n_lines == n_frames:
        data = values.reshape(n_frames, n_channels)
        bad = ~np.isfinite(data)
        if bad.any():
            row = int(np.flatnonzero(bad.any(axis=1))[0])
            line_no = _data_line_number(block.split("\n"), row) + first + 1
            raise MotionFileError(
                f"frame {row} holds NaN or infinite values", path=path, line=line_no, code="bvh_nan"
            )
        return data
    body = block.split("\n") if block else []
    # Slow path: find the first line that breaks the layout.
    row = 0
    for i, line in enumerate(body):
        toks = line.split()
        if not toks:
            continue
        line_no = first + i + 1
        if row >= n_frames:
            raise MotionFileError(
                f"more frame lines than the {n_frames} declared",
                path=path,
                line=line_no,
                code="bvh_frame_count",
            )
        if i == len(body) - 1 and len(toks) < n_channels and row < n_frames:
            raise MotionFileError(
                f"file ends inside frame {row} ({len(toks)} of {n_channels} values)",
                path=path,
                line=line_no,
                code="bvh_truncated",
            )
        for tok in toks:
            if not _FLOAT_RE.match(tok):
                code = (
                    "bvh_nan"
                    if tok.lower().lstrip("+-") in {"nan", "inf", "infinity"}
                    else "bvh_syntax"
                )
                raise MotionFileError(
                    f"frame {row}: {tok!r} is not a finite number",
                    path=path,
                    line=line_no,
                    code=code,
                )
        if len(toks) != n_channels:
            raise MotionFileError(
                f"frame {row} has {len(toks)} values, the hierarchy declares {n_channels} channels",
                path=path,
                line=line_no,
                code="bvh_channel_count",
            )
        row += 1
    raise MotionFileError(
        f"file ends after {row} of {n_frames} declared frames",
        path=path,
        line=first + len(body),
        code="bvh_truncated" if row < n_frames else "bvh_syntax",
    )


def _data_line_number(body: list[str], row: int) -> int:
    """0-based index in ``body`` of the ``row``-th non-blank line."""
    seen = -1
    for i, line in enumerate(body):
        if line.strip():
            seen += 1
            if seen == row:
                return i
    return len(body) - 1


def _channels_to_pose(
    data: np.ndarray, skeleton: Skeleton, scale: float
) -> tuple[np.ndarray, np.ndarray]:
    n_frames = data.shape[0]
    n_joints = skeleton.n_joints
    root_positions = np.tile(skeleton.offsets[0], (n_frames, 1))
    rotations = np.zeros((n_frames, n_joints, 4))
    rotations[..., 3] = 1.0
    # Group joints by Euler order so each group converts in one scipy call.
    groups: dict[str, tuple[list[int], list[list[int]]]] = {}
    col = 0
    for j, chans in enumerate(skeleton.channels):
        rot_cols = [col + k for k, c in enumerate(chans) if c in _ROTATION]
        if j == 0:
            pos_cols = {_POSITION[c]: col + k for k, c in enumerate(chans) if c in _POSITION}
            if pos_cols:
                root_positions = data[:, [pos_cols["X"], pos_cols["Y"], pos_cols["Z"]]] * scale
        if rot_cols:
            order = _euler_order(chans)
            joints, cols = groups.setdefault(order, ([], []))
            joints.append(j)
            cols.append(rot_cols)
        col += len(chans)
    for order, (joints, cols) in groups.items():
        angles = data[:, np.asarray(cols)]  # (F, G, 3)
        rotations[:, joints] = quat.from_euler(order, angles)
    return root_positions, rotations


def pose_to_channels(motion: Motion) -> np.ndarray:
    """``(F, C)`` BVH channel values (degrees; root position in metres) in the skeleton's layout.

    Euler angles are unwrapped along time so curves stay continuous in animation tools.
    """
    skeleton = motion.skeleton
    n_frames = motion.n_frames
    n_channels = sum(len(c) for c in skeleton.channels)
    data = np.zeros((n_frames, n_channels))
    groups: dict[str, tuple[list[int], list[list[int]]]] = {}
    col = 0
    for j, chans in enumerate(skeleton.channels):
        for k, c in enumerate(chans):
            if c in _POSITION:
                axis = "XYZ".index(_POSITION[c])
                data[:, col + k] = (
                    motion.root_positions[:, axis] if j == 0 else skeleton.offsets[j, axis]
                )
        rot_cols = [col + k for k, c in enumerate(chans) if c in _ROTATION]
        if rot_cols:
            joints, cols = groups.setdefault(_euler_order(chans), ([], []))
            joints.append(j)
            cols.append(rot_cols)
        col += len(chans)
    for order, (joints, cols) in groups.items():
        quats = motion.rotations[:, joints].reshape(-1, 4)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # gimbal lock: any valid angle set is fine
            angles = Rotation.from_quat(quats).as_euler(order, degrees=True)
        angles = np.unwrap(angles.reshape(n_frames, len(joints), 3), period=360.0, axis=0)
        data[:, np.asarray(cols)] = angles
    return data


def _fmt(x: float) -> str:
    s = f"{x:.6f}"
    return "0.000000" if s == "-0.000000" else s


def write_bvh(motion: Motion, path: str | Path) -> None:
    """Write ``motion`` as BVH (metres, the skeleton's own channel orders), atomically."""
    skeleton = motion.skeleton
    path = Path(path)
    out: list[str] = ["HIERARCHY"]
    children: dict[int, list[int]] = {}
    for j, p in enumerate(skeleton.parents):
        children.setdefault(int(p), []).append(j)

    def emit(j: int, depth: int) -> None:
        ind = "\t" * depth
        keyword = "ROOT" if skeleton.parents[j] < 0 else "JOINT"
        out.append(f"{ind}{keyword} {skeleton.names[j]}")
        out.append(f"{ind}{{")
        off = " ".join(_fmt(v) for v in skeleton.offsets[j])
        out.append(f"{ind}\tOFFSET {off}")
        chans = skeleton.channels[j]
        out.append(f"{ind}\tCHANNELS {len(chans)}" + "".join(f" {c}" for c in chans))
        for c in children.get(j, []):
            emit(c, depth + 1)
        if j in skeleton.end_sites:
            end = " ".join(_fmt(v) for v in skeleton.end_sites[j])
            out.extend([f"{ind}\tEnd Site", f"{ind}\t{{", f"{ind}\t\tOFFSET {end}", f"{ind}\t}}"])
        out.append(f"{ind}}}")

    for root in children.get(-1, []):
        emit(root, 0)
    out.append("MOTION")
    out.append(f"Frames: {motion.n_frames}")
    out.append(f"Frame Time: {1.0 / motion.fps:.8f}")
    data = pose_to_channels(motion)
    data[np.abs(data) < 5e-7] = 0.0  # no "-0.000000"
    fmt = " ".join(["%.6f"] * data.shape[1])
    body = "\n".join(fmt % tuple(row) for row in data.tolist())
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(out) + "\n" + body + "\n")
    tmp.replace(path)
