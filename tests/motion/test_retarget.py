"""Retargeting real salsa onto the project's test rigs, checked on the files written.

Every number is measured on what a user gets: the BVH read back by DanceGraph's reader, the GLB
read by pygltflib (an independent glTF loader) and skinned by hand, the FBX read by ufbx (an
independent FBX reader, in a child process because its binding can crash on exit).
"""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dancegraph.cli import main as cli_main
from dancegraph.motion import quat
from dancegraph.motion.bvh import read_bvh
from dancegraph.motion.contacts import foot_contacts
from dancegraph.motion.fbx import fbx_available
from dancegraph.motion.fk import forward_kinematics
from dancegraph.motion.retarget import (
    RetargetParams,
    plan_retarget,
    retarget,
    write_on_rig,
)
from dancegraph.motion.rig import SIDES, foot_points, load_rig
from tests.motion.rigs import GOOD_BVH_RIGS, GOOD_RIGS, GOOD_RIGS_MESH, PARENTED_RIGS
from tests.motion.ufbx_child import ufbx_json

needs_blender = pytest.mark.skipif(not fbx_available(), reason="Blender not installed")
ALL_RIGS = [
    pytest.param(n, marks=needs_blender) for n in GOOD_RIGS + GOOD_RIGS_MESH + PARENTED_RIGS
] + list(GOOD_BVH_RIGS)


def _file_checks(source, rig, motion) -> dict:
    """Issue 21's checks from a motion on the rig (rig axes), against the source."""
    pos, g = forward_kinematics(motion)
    canon = quat.rotate(np.broadcast_to(rig.to_canonical, pos.shape[:-1] + (4,)), pos)
    g_c = quat.multiply(
        quat.multiply(rig.to_canonical, g), quat.conjugate(rig.to_canonical)[None, None]
    )
    plan = plan_retarget(source.skeleton, rig)
    src_pos, src_g = forward_kinematics(source)
    src_c = quat.rotate(np.broadcast_to(plan.src_to_canon, src_pos.shape[:-1] + (4,)), src_pos)
    contacts = foot_contacts(src_pos, source.fps, source.skeleton, src_g)
    sole_err, slide = [], []
    for s, side in enumerate(SIDES):
        pts = []
        for j, off in foot_points(plan.target, rig.roles.roles, side):
            p = canon[:, j]
            if np.any(off):
                p = p + quat.rotate(g_c[:, j], np.broadcast_to(off, p.shape))
            pts.append(p)
        pts = np.stack(pts, axis=1)
        rest = rig.canonical_positions()
        clearance = np.array(
            [
                rest[j, 1] + off[1] - rig.floor
                for j, off in foot_points(plan.target, rig.roles.roles, side)
            ]
        )
        above = pts[..., 1] - clearance - rig.floor
        mask = contacts[:, s]
        sole_err.append(above.min(axis=1)[mask])
        lowest = np.argmin(above, axis=1)
        step = np.linalg.norm(np.diff(pts[np.arange(len(pts)), lowest][:, [0, 2]], axis=0), axis=1)
        both = mask[1:] & mask[:-1] & (lowest[1:] == lowest[:-1])
        slide.append(step[both])
    angles = []
    for _role, s, se, t, te in plan.limbs:
        a, b = src_c[:, se] - src_c[:, s], canon[:, te] - canon[:, t]
        cos = np.sum(a * b, -1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    return {
        "floor_max_m": float(np.abs(np.concatenate(sole_err)).max()),
        "slide_median_m_s": float(np.median(np.concatenate(slide)) * source.fps),
        "direction_median_deg": float(np.median(np.concatenate(angles))),
        "contact_frames": int(contacts.sum()),
    }


@pytest.mark.parametrize("name", ALL_RIGS)
def test_targets_on_every_rig(rig_dir, salsa_clip, tmp_path, name):
    rig = load_rig(rig_dir / name)
    motion, report = retarget(salsa_clip, rig)
    assert np.isfinite(motion.rotations).all() and np.isfinite(motion.root_positions).all()
    assert motion.n_frames == salsa_clip.n_frames and motion.skeleton is rig.skeleton
    # the report's own numbers
    assert report["floor_error_m"]["max_abs"] <= 0.01
    assert report["sliding_m_s"] <= report["source_sliding_m_s"]
    assert report["direction_error_deg"]["median"] <= 5.0
    steps = report["max_joint_step_deg"]
    assert steps["target"] <= steps["source"] + 1.0  # no flips beyond what the dance does
    # and the same checks from the BVH file a user gets
    write_on_rig(motion, rig, rig_dir / name, tmp_path / "out.bvh")
    back = read_bvh(tmp_path / "out.bvh", scale=rig.unit_scale)
    back.skeleton.canonical = rig.skeleton.canonical
    checks = _file_checks(salsa_clip, rig, back)
    assert checks["contact_frames"] > 500
    assert checks["floor_max_m"] <= 0.01
    assert checks["slide_median_m_s"] <= 0.01
    assert checks["direction_median_deg"] <= 5.0


def test_without_foot_ik_the_feet_miss_the_floor(rig_dir, salsa_clip):
    """The foot step is what puts the feet on the floor: rotations alone leave them off by cm."""
    rig = load_rig(rig_dir / "cmu_cm.bvh")
    _, report = retarget(salsa_clip, rig, RetargetParams(foot_ik=False))
    assert report["floor_error_m"]["max_abs"] > 0.01
    assert report["sliding_m_s"] > report["source_sliding_m_s"]


def test_bvh_rig_output_keeps_its_units(rig_dir, salsa_clip, tmp_path):
    rig = load_rig(rig_dir / "cmu_cm.bvh")
    motion, _ = retarget(salsa_clip.slice(0, 60), rig)
    write_on_rig(motion, rig, rig_dir / "cmu_cm.bvh", tmp_path / "cm.bvh")
    back = read_bvh(tmp_path / "cm.bvh")
    original = read_bvh(rig_dir / "cmu_cm.bvh")
    assert back.skeleton.names == original.skeleton.names
    assert np.allclose(back.skeleton.offsets[1:], original.skeleton.offsets[1:], atol=1e-4)


# --- GLB ----------------------------------------------------------------------------------------


def _glb_world(path, frames: list[int]):
    """Node world matrices per frame, skinned vertex positions, from pygltflib's parse alone."""
    pygltflib = pytest.importorskip("pygltflib")
    gltf = pygltflib.GLTF2().load(str(path))
    blob = gltf.binary_blob()

    def accessor(k):
        acc = gltf.accessors[k]
        view = gltf.bufferViews[acc.bufferView]
        dtype = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}[acc.componentType]
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[acc.type]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        return np.frombuffer(blob, dtype, acc.count * width, start).reshape(acc.count, width)

    anim = gltf.animations[0]
    tracks = {}
    for ch in anim.channels:
        sampler = anim.samplers[ch.sampler]
        tracks[(ch.target.node, ch.target.path)] = accessor(sampler.output)
    parent = {c: i for i, n in enumerate(gltf.nodes) for c in (n.children or [])}
    out = []
    for f in frames:
        local = []
        for i, node in enumerate(gltf.nodes):
            if node.matrix is not None:  # the rig's ancestors: a static matrix each
                local.append(np.asarray(node.matrix, dtype=float).reshape(4, 4).T)
                continue
            t = tracks.get((i, "translation"), [node.translation or [0, 0, 0]] * (f + 1))[f]
            r = tracks.get((i, "rotation"), [node.rotation or [0, 0, 0, 1]] * (f + 1))[f]
            m = np.eye(4)
            m[:3, :3] = Rotation.from_quat(r).as_matrix() * np.asarray(node.scale or [1, 1, 1])
            m[:3, 3] = t
            local.append(m)
        world = [None] * len(local)

        def w(i, local=local, world=world):
            if world[i] is None:
                world[i] = local[i] if i not in parent else w(parent[i]) @ local[i]
            return world[i]

        out.append(np.stack([w(i) for i in range(len(local))]))
    skinned = None
    if gltf.skins:
        skin = gltf.skins[0]
        prim = gltf.meshes[0].primitives[0]
        pos = accessor(prim.attributes.POSITION).astype(float)
        jts = accessor(prim.attributes.JOINTS_0).astype(int)
        wts = accessor(prim.attributes.WEIGHTS_0).astype(float)
        ibm = accessor(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
        skinned = []
        for world in out:
            mats = world[skin.joints] @ ibm
            homo = np.concatenate([pos, np.ones((len(pos), 1))], axis=1)
            v = np.einsum("vkij,vj->vki", mats[jts], homo)[..., :3]
            skinned.append(np.sum(v * wts[..., None], axis=1))
    names = [n.name for n in gltf.nodes]
    return names, out, skinned


@pytest.mark.parametrize("name", [pytest.param("skinned.fbx", marks=needs_blender), "cmu_cm.bvh"])
def test_glb_on_rig_reads_back(rig_dir, salsa_clip, tmp_path, name):
    rig = load_rig(rig_dir / name)
    motion, _ = retarget(salsa_clip.slice(0, 240), rig)
    summary = write_on_rig(motion, rig, rig_dir / name, tmp_path / "dance.glb")
    assert summary["frames"] == 240
    frames = [0, 97, 239]
    names, worlds, skinned = _glb_world(tmp_path / "dance.glb", frames)
    pos, _ = forward_kinematics(motion)
    for k, f in enumerate(frames):
        got = np.array([worlds[k][names.index(n)][:3, 3] for n in rig.skeleton.names])
        assert np.abs(got - pos[f]).max() < 1e-4
    if rig.mesh is not None:
        # at the first frame the skin sits near the bind pose; later the body has moved
        moved = np.linalg.norm(skinned[1] - skinned[0], axis=1)
        assert np.median(moved) > 0.05
        # every vertex follows its bone: distance to its main joint is kept from bind
        main = rig.mesh.joints[:, 0]
        bind_d = np.linalg.norm(rig.mesh.positions - _bind(rig)[main], axis=1)
        d = np.linalg.norm(skinned[1] - pos[97][main], axis=1)
        rigid = rig.mesh.weights[:, 0] > 0.99
        assert np.abs(d - bind_d)[rigid].max() < 1e-3
    # the GLB is also a rig: it loads back with the same joints and roles
    again = load_rig(tmp_path / "dance.glb")
    assert again.skeleton.names == rig.skeleton.names
    assert again.roles.roles == rig.roles.roles


def _bind(rig):
    from dancegraph.motion.rig import bind_positions

    return bind_positions(rig)


@pytest.mark.parametrize(
    "name",
    [
        pytest.param("skinned.fbx", marks=needs_blender),
        pytest.param("parented.glb", marks=needs_blender),  # ancestors written as matrices
        "cmu_cm.bvh",
    ],
)
def test_glb_passes_the_khronos_validator(rig_dir, salsa_clip, tmp_path, name):
    """The official glTF validator (npm ``gltf-validator``, installed with the preview page)."""
    from dancegraph.paths import REPO_ROOT

    module = REPO_ROOT / "frontend" / "node_modules" / "gltf-validator"
    if not module.is_dir() or shutil.which("node") is None:
        pytest.skip("gltf-validator not installed (scripts/install-frontend.sh)")
    rig = load_rig(rig_dir / name)
    motion, _ = retarget(salsa_clip.slice(0, 120), rig)
    write_on_rig(motion, rig, rig_dir / name, tmp_path / "dance.glb")
    script = (
        "const v=require(process.argv[1]);const fs=require('fs');"
        "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[2])))"
        ".then(r=>{console.log(JSON.stringify(r.issues));})"
        ".catch(e=>{console.error(e);process.exit(1);});"
    )
    proc = subprocess.run(
        ["node", "-e", script, str(module), str(tmp_path / "dance.glb")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    issues = json.loads(proc.stdout)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]


# --- FBX ----------------------------------------------------------------------------------------

_UFBX_READER = r"""
import json, os, sys, ufbx
path, frames = sys.argv[1], json.loads(sys.argv[2])
scene = ufbx.load_file(path, target_axes=ufbx.axes_right_handed_y_up, target_unit_meters=1.0,
                       space_conversion=ufbx.SpaceConversion.ADJUST_TRANSFORMS)
fps = scene.settings.frames_per_second
stack = scene.anim_stacks[0]
out = {"fps": fps, "duration": stack.time_end - stack.time_begin, "positions": {}, "verts": {}}
alive = [scene]
for f in frames:
    ev = ufbx.evaluate_scene(scene, scene.anim, f / fps, evaluate_skinning=True)
    alive.append(ev)
    nodes = [ev.nodes[i] for i in range(len(ev.nodes))]
    alive.append(nodes)
    out["positions"][str(f)] = {
        n.name: [n.node_to_world.c3.x, n.node_to_world.c3.y, n.node_to_world.c3.z]
        for n in nodes if n.bone is not None
    }
    meshes = [ev.meshes[i] for i in range(len(ev.meshes))]
    alive.append(meshes)
    verts = []
    for m in meshes:
        vals = m.skinned_position.values
        verts += [[vals[i].x, vals[i].y, vals[i].z] for i in range(len(vals))]
    out["verts"][str(f)] = verts
sys.stdout.write(json.dumps(out) + "\n")
sys.stdout.flush()
os._exit(0)  # the binding can crash while freeing evaluated scenes
"""


@needs_blender
@pytest.mark.parametrize("name", ["unreal.fbx", "skinned.fbx", "skinned.glb", "cmu_cm.bvh"])
def test_fbx_on_rig_reads_back_with_ufbx(rig_dir, salsa_clip, tmp_path, name):
    """Unreal: A-pose, Z up, facing +Y, twist bones; skinned: the mesh deforms; GLB/BVH rigs too."""
    rig = load_rig(rig_dir / name)
    other, _ = retarget(salsa_clip.slice(600, 700), rig)  # the warm worker keeps the rig loaded:
    write_on_rig(other, rig, rig_dir / name, tmp_path / "other.fbx")  # nothing of it may remain
    motion, _ = retarget(salsa_clip.slice(0, 180), rig)
    summary = write_on_rig(motion, rig, rig_dir / name, tmp_path / "dance.fbx")
    assert summary["frames"] == 180
    frames = [0, 90, 179]
    fbx = ufbx_json(_UFBX_READER, tmp_path / "dance.fbx", frames)
    assert fbx["fps"] == pytest.approx(60.0)
    assert round(fbx["duration"] * fbx["fps"]) + 1 == 180
    pos, _ = forward_kinematics(motion)
    for f in frames:
        got = fbx["positions"][str(f)]
        assert set(rig.skeleton.names) <= set(got)
        err = max(
            np.linalg.norm(np.array(got[n]) - pos[f, j]) for j, n in enumerate(rig.skeleton.names)
        )
        assert err < 1e-3, (f, err)
    if rig.mesh is not None:
        v0, v1 = np.array(fbx["verts"]["0"]), np.array(fbx["verts"]["90"])
        assert len(v0) >= rig.mesh.n_vertices and np.median(np.linalg.norm(v1 - v0, axis=1)) > 0.05


# --- CLI ----------------------------------------------------------------------------------------


def test_cli_retarget(rig_dir, salsa_dir, tmp_path, capsys):
    src = tmp_path / "dance.bvh"
    from dancegraph.motion.bvh import write_bvh

    write_bvh(read_bvh(salsa_dir / "60_02_scaled.bvh", fps=60).slice(0, 300), src)
    out = tmp_path / "on_rig.glb"
    rc = cli_main(["retarget", str(src), "--rig", str(rig_dir / "cmu_cm.bvh"), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    printed = json.loads(capsys.readouterr().out)
    assert out.stat().st_size > 10_000 and printed["written"]["frames"] == 300
    assert printed["rig"]["roles"]["left_knee"] == "lShin"
    assert printed["report"]["direction_error_deg"]["median"] <= 5.0
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({"head": "nope"}))
    args = ["retarget", str(src), "--rig", str(rig_dir / "cmu_cm.bvh"), "--out", str(out)]
    assert cli_main([*args, "--map", str(mapping)]) == 2
    assert "rig_map_invalid" in capsys.readouterr().err
    bad = ["retarget", str(src), "--rig", str(rig_dir / "bad_zero_length.bvh"), "--out", str(out)]
    assert cli_main(bad) == 2
    assert "rig_zero_length" in capsys.readouterr().err
    assert cli_main([*args[:-1], str(tmp_path / "x.obj")]) == 2
    assert "rig_output_format" in capsys.readouterr().err


def test_hand_ik_puts_the_hands_where_the_source_has_them(rig_dir, salsa_clip):
    """Optional: wrists at the source's place relative to the hips (scaled); off by default."""
    rig = load_rig(rig_dir / "cmu_cm.bvh")  # arms 1.1 x the template's: rotations alone miss
    plan = plan_retarget(salsa_clip.skeleton, rig)

    def hand_miss(motion) -> float:
        pos, _ = forward_kinematics(motion)
        canon = quat.rotate(np.broadcast_to(rig.to_canonical, pos.shape[:-1] + (4,)), pos)
        src, _ = forward_kinematics(salsa_clip)
        src = quat.rotate(np.broadcast_to(plan.src_to_canon, src.shape[:-1] + (4,)), src)
        miss = []
        for _s, _e, wrist, src_wrist in plan.arms:
            goal = canon[:, plan.hips] + plan.ratio * (src[:, src_wrist] - src[:, plan.src_hips])
            miss.append(np.linalg.norm(canon[:, wrist] - goal, axis=1))
        return float(np.median(np.concatenate(miss)))

    plain, _ = retarget(salsa_clip, rig)
    with_ik, report = retarget(salsa_clip, rig, RetargetParams(hand_ik=True))
    assert hand_miss(plain) > 0.02
    assert hand_miss(with_ik) < 1e-3 and report["hand_error_m"]["median"] < 1e-3
    assert np.isfinite(with_ik.rotations).all()
    assert report["floor_error_m"]["max_abs"] <= 0.01  # the feet are not disturbed


# --- rigs under parent transforms ---------------------------------------------------------------


def _truth(name: str) -> dict[str, np.ndarray]:
    """The test rig's joints where its generator put them: world metres, Y up."""
    from tests.motion.rigs import rig_specs

    spec = next(s for s in rig_specs() if s["name"] == name)
    return {b["name"]: np.array([b["head"][0], b["head"][2], -b["head"][1]]) for b in spec["bones"]}


def _world_checks(rig, motion, frames: list[int], got: np.ndarray) -> dict:
    """Issue 38's checks on world positions read back from a file: ``got (len(frames), J, 3)``."""
    pos, g = forward_kinematics(motion)
    pos, g = pos[frames], g[frames]
    height = np.ptp(got[..., 1], axis=1) / np.ptp(pos[..., 1], axis=1)
    hips, head = rig.joint("hips"), rig.joint("head")

    def tilt_deg(p: np.ndarray) -> np.ndarray:  # hips-to-head direction against world +Y
        up = p[:, head] - p[:, hips]
        return np.degrees(np.arccos(up[:, 1] / np.linalg.norm(up, axis=1)))

    tilt = tilt_deg(got)
    floor = []
    rest = rig.canonical_positions()
    for side in SIDES:
        points = foot_points(rig.skeleton, rig.roles.roles, side)
        heights = np.stack(
            [
                got[:, j, 1]
                + quat.rotate(g[:, j], np.broadcast_to(off, (len(frames), 3)))[:, 1]
                - (rest[j, 1] + off[1] - rig.floor)
                for j, off in points
            ],
            axis=1,
        )
        floor.append(heights.min(axis=1) - rig.floor)
    return {
        "joint_error_m": float(np.abs(got - pos).max()),
        "height_ratio_error": float(np.abs(height - 1.0).max()),
        "tilt_median_deg": float(np.median(tilt)),  # a standing dance: upright on the whole
        "tilt_vs_dance_deg": float(np.abs(tilt - tilt_deg(pos)).max()),
        "sole_m": np.stack(floor, axis=1),  # (frames, 2): lowest foot point above the floor
    }


@needs_blender
@pytest.mark.parametrize("name", PARENTED_RIGS)
def test_rigs_under_parent_transforms_land_where_they_stood(rig_dir, salsa_clip, tmp_path, name):
    """A centimetre, Z-up glTF armature under a turned, scaled node and a centimetre FBX with
    pre- and post-rotations: read at their size in world space, written under the same parents,
    and every written file stands upright with its feet on the floor."""
    rig = load_rig(rig_dir / name)
    truth = _truth(name.split(".")[0])
    bind = {n: p for n, p in zip(rig.skeleton.names, _bind(rig), strict=True)}
    assert max(np.linalg.norm(bind[n] - truth[n]) for n in truth) < 1e-3
    true_height = max(p[1] for p in truth.values()) - min(p[1] for p in truth.values())
    assert abs(np.ptp(_bind(rig)[:, 1]) / true_height - 1.0) < 0.02
    assert rig.up_axis() == "+Y" and rig.ancestors
    motion, report = retarget(salsa_clip, rig)
    assert abs(report["world"]["height_m"] / rig.height() - 1.0) < 1e-6 and rig.height() < 2.0
    src_pos, src_g = forward_kinematics(salsa_clip)
    contacts = foot_contacts(src_pos, salsa_clip.fps, salsa_clip.skeleton, src_g)
    frames = list(range(0, motion.n_frames, 7))
    files = {fmt: tmp_path / f"dance.{fmt}" for fmt in ("bvh", "glb", "usda", "fbx")}
    for path in files.values():
        summary = write_on_rig(motion, rig, rig_dir / name, path)
        assert summary["placement"]["height_ratio"] == pytest.approx(1.0, abs=0.02)
        assert summary["placement"]["upright"]
    back = read_bvh(files["bvh"], scale=rig.unit_scale)
    got = {"bvh": forward_kinematics(back)[0][frames]}
    names, worlds, _ = _glb_world(files["glb"], frames)
    assert [n.name for n in _gltf_nodes(files["glb"])][: len(rig.ancestors)] == [
        a for a, _ in rig.ancestors
    ]
    got["glb"] = np.stack([[w[names.index(n)][:3, 3] for n in rig.skeleton.names] for w in worlds])
    got["usda"] = _usd_world(files["usda"], frames)
    few = frames[::10]
    fbx = ufbx_json(_UFBX_READER, files["fbx"], few)["positions"]
    got["fbx"] = np.array([[fbx[str(f)][n] for n in rig.skeleton.names] for f in few])
    for fmt, positions in got.items():
        checked = frames if fmt != "fbx" else few
        c = _world_checks(rig, motion, checked, positions)
        assert c["joint_error_m"] < 1e-3, (fmt, c["joint_error_m"])
        assert c["height_ratio_error"] < 0.02, (fmt, c)
        assert c["tilt_median_deg"] < 15.0 and c["tilt_vs_dance_deg"] < 1.0, (fmt, c)
        planted = contacts[checked]
        assert np.abs(c["sole_m"][planted]).max() < 0.01, fmt
        assert (c["sole_m"] > -0.01).all(), fmt


def _gltf_nodes(path):
    pygltflib = pytest.importorskip("pygltflib")
    return pygltflib.GLTF2().load(str(path)).nodes


def _usd_world(path, frames: list[int]) -> np.ndarray:
    """Joint world positions (metres) from pxr's UsdSkel alone, at ``frames``."""
    pxr = pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom, UsdSkel

    del pxr
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    skel = next(UsdSkel.Skeleton(p) for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
    query = UsdSkel.Cache().GetSkelQuery(skel)
    out = []
    for f in frames:
        xf = UsdGeom.XformCache(Usd.TimeCode(f))
        out.append(np.array(query.ComputeJointWorldTransforms(xf))[:, 3, :3])
    return np.stack(out)


def test_a_misplaced_output_is_an_error(rig_dir, salsa_clip, tmp_path):
    """The output is read back: a character written at the wrong size is refused and removed."""
    from dancegraph.motion.retarget import check_placement
    from dancegraph.motion.rig import RigError

    rig = load_rig(rig_dir / "cmu_cm.bvh")
    motion, _ = retarget(salsa_clip.slice(0, 30), rig)
    first = forward_kinematics(motion.slice(0, 1))[0][0]
    assert check_placement(rig, motion, first)["height_ratio"] == pytest.approx(1.0)
    partly = first.copy()
    partly[rig.joint("head")] = np.nan  # a joint the file does not name is left out
    placed = check_placement(rig, motion, partly)
    assert placed["height_ratio"] == pytest.approx(1.0) and placed["up_error_deg"] < 1.0
    with pytest.raises(RigError) as err:
        check_placement(rig, motion, first * 100.0)  # centimetres taken for metres
    assert err.value.code == "rig_output_scale"
    lying = first[:, [0, 2, 1]] * [1, 1, -1]  # a Z-up frame never turned upright
    with pytest.raises(RigError) as err:
        check_placement(rig, motion, lying)
    assert err.value.code in ("rig_output_not_upright", "rig_output_scale")
    with pytest.raises(RigError) as err:
        check_placement(rig, motion, first + [0.0, 0.3, 0.0])
    assert err.value.code == "rig_output_floor"
