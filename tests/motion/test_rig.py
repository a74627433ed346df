"""Rigs in: FBX, GLB and BVH files made by the project, their humanoid roles, and bad rigs refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dancegraph.motion.fbx import fbx_available
from dancegraph.motion.rig import (
    REQUIRED_ROLES,
    RigError,
    bind_positions,
    build_rig,
    load_rig,
    map_roles,
    normalize_name,
    read_mapping,
)
from tests.motion.rigs import BAD_RIGS, GOOD_BVH_RIGS, GOOD_RIGS, GOOD_RIGS_MESH

needs_blender = pytest.mark.skipif(not fbx_available(), reason="Blender not installed")

EXPECTED_PRESET = {
    "mixamo.fbx": "mixamo",
    "unreal.fbx": "unreal",
    "rigify.fbx": "rigify",
    "child.fbx": "mixamo",
    "fingers.fbx": "mixamo",
    "skinned.fbx": "unity",
    "skinned.glb": "unity",
    "cmu_cm.bvh": "cmu",
}


def _check_rig(rig, name: str) -> None:
    assert all(r in rig.roles.roles for r in REQUIRED_ROLES)
    assert set(rig.roles.how.values()) == {f"preset:{EXPECTED_PRESET[name]}"}
    # canonical frame: hips above the feet, head above the hips, left leg on +X
    pos = rig.canonical_positions()
    j = rig.joint
    assert pos[j("head"), 1] > pos[j("hips"), 1] > pos[j("left_ankle"), 1]
    assert pos[j("left_hip"), 0] > pos[j("right_hip"), 0]
    assert 0.9 < rig.height() < 2.0 and abs(rig.floor) < 0.05


@needs_blender
@pytest.mark.parametrize("name", GOOD_RIGS + GOOD_RIGS_MESH)
def test_blender_made_rigs_load_with_their_roles(rig_dir, name):
    rig = load_rig(rig_dir / name)
    _check_rig(rig, name)
    if name.startswith("skinned"):
        assert rig.mesh is not None and rig.mesh.n_vertices > 100
        assert np.allclose(rig.mesh.weights.sum(axis=1), 1.0, atol=1e-5)
    else:
        assert rig.mesh is None
    if name == "unreal.fbx":  # twist and IK bones are listed, not mapped
        assert {"upperarm_twist_01_l", "thigh_twist_01_r", "ik_foot_root", "root"} <= set(
            rig.roles.unmapped
        )
    if name == "mixamo.fbx":  # centimetres in the file, metres here
        assert rig.skeleton.names[0] == "mixamorig:Hips"
        assert 1.0 < rig.canonical_positions()[rig.joint("hips"), 1] < 1.1


def test_bvh_rig_in_centimetres(rig_dir):
    rig = load_rig(rig_dir / GOOD_BVH_RIGS[0])
    _check_rig(rig, GOOD_BVH_RIGS[0])
    assert rig.unit_scale == pytest.approx(0.01)
    assert set(rig.summary()["missing_optional"]) == {"upper_chest", "left_toe", "right_toe"}


@pytest.mark.parametrize("name,code", sorted(BAD_RIGS.items()))
def test_bad_rigs_get_their_code(rig_dir, name, code):
    if name.endswith(".fbx") and not fbx_available():
        pytest.skip("Blender not installed")
    with pytest.raises(RigError) as err:
        load_rig(rig_dir / name)
    assert err.value.code == code and err.value.status == 422
    if code == "rig_missing_roles":
        assert "left_hip" in err.value.field


def test_unreadable_and_unknown_files(tmp_path):
    junk = tmp_path / "junk.fbx"
    junk.write_bytes(b"\x00not an fbx at all" * 10)
    with pytest.raises(RigError) as err:
        load_rig(junk)
    assert err.value.code == "rig_unreadable"
    glb = tmp_path / "junk.glb"
    glb.write_bytes(b"glTF\x02\x00\x00\x00")
    with pytest.raises(RigError) as err:
        load_rig(glb)
    assert err.value.code == "rig_unreadable"
    with pytest.raises(RigError) as err:
        load_rig(tmp_path / "rig.obj")
    assert err.value.code == "rig_format"


def test_name_normalisation():
    assert normalize_name("mixamorig:LeftArm") == "leftarm"
    assert normalize_name("mixamorig_LeftArm") == "leftarm"
    assert normalize_name("Armature|mixamorig1:LeftArm") == "leftarm"
    assert normalize_name("DEF-thigh.L") == "thigh.l"


def test_structure_finds_the_roles_without_names(rig_dir):
    """Names no preset knows: the hierarchy's shape and the bind pose give the same roles."""
    rig = load_rig(rig_dir / "cmu_cm.bvh")
    sk = rig.skeleton
    pos = bind_positions(rig)
    anonymous = [f"bone{j:02d}" for j in range(sk.n_joints)]
    found = map_roles(anonymous, sk.parents, pos)
    assert set(found.how.values()) == {"structure"}
    renamed = {r: anonymous[sk.index(n)] for r, n in rig.roles.roles.items()}
    for role in (*REQUIRED_ROLES, "head", "left_shoulder", "left_elbow", "left_wrist"):
        assert found.roles[role] == renamed[role], role
    # turned to face -X and lying on its Z axis: still the same roles
    from scipy.spatial.transform import Rotation

    turned = Rotation.from_euler("xy", [90, -90], degrees=True).apply(pos)
    found = map_roles(anonymous, sk.parents, turned)
    for role in REQUIRED_ROLES:
        assert found.roles[role] == renamed[role], role


def test_user_mapping_overrides_and_is_checked(rig_dir, tmp_path):
    rig = load_rig(rig_dir / "cmu_cm.bvh", mapping={"head": "neck"})
    assert rig.roles.roles["head"] == "neck" and rig.roles.how["head"] == "user"
    assert "neck" not in rig.roles.roles  # a joint plays one role
    bad = tmp_path / "map.json"
    bad.write_text(json.dumps({"left_elbowz": "lForeArm"}))
    with pytest.raises(RigError) as err:
        read_mapping(bad)
    assert err.value.code == "rig_map_invalid" and err.value.field == "left_elbowz"
    with pytest.raises(RigError) as err:
        load_rig(rig_dir / "cmu_cm.bvh", mapping={"head": "no_such_joint"})
    assert err.value.code == "rig_map_invalid"
    yaml_map = tmp_path / "map.yaml"
    yaml_map.write_text("left_elbow: lForeArm\n")
    assert read_mapping(yaml_map) == {"left_elbow": "lForeArm"}


def test_build_rig_refuses_degenerate_input():
    with pytest.raises(RigError) as err:
        build_rig([], np.zeros(0), np.zeros((0, 4, 4)))
    assert err.value.code == "rig_no_armature"
    mats = np.tile(np.eye(4), (2, 1, 1))
    mats[0, 0, 3] = np.nan
    with pytest.raises(RigError) as err:
        build_rig(["a", "b"], np.array([-1, 0]), mats)
    assert err.value.code == "rig_degenerate"
