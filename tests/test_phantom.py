"""Phantom geometry: watertight, and consistent with the mechanism (the condyles touch the facets)."""

import numpy as np
import open3d as o3d
import pytest

from knee.foundations.conventions import joint_to_pose
from knee.models.phantom import build_phantom, posed_bones


def _signed_distance(mesh, points):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(mesh.faces.astype(np.uint32)))
    return scene.compute_signed_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


@pytest.fixture(scope="module")
def phantoms(volunteer, generic):
    return {"volunteer": (volunteer, build_phantom(volunteer.params)),
            "generic": (generic, build_phantom(generic.params))}


@pytest.mark.parametrize("name", ["volunteer", "generic"])
def test_watertight(phantoms, name):
    mech, ph = phantoms[name]
    for bone in (ph.femur, ph.tibia) + ((ph.patella,) if ph.patella is not None else ()):
        assert bone.is_watertight and bone.is_volume and bone.volume > 0
    tf, pf, _ = mech.solve(np.radians(45))
    skin = ph.skin(joint_to_pose(tf), joint_to_pose(pf) if mech.has_pf else None)
    assert skin.is_watertight
    # the envelope holds the posed bones near the knee
    bones = posed_bones(ph, tf, pf)
    near = bones["femur"].vertices[bones["femur"].vertices[:, 1] < 60]
    assert np.all(_signed_distance(skin, near) < 0)


def test_condyles_are_spheres_at_the_contact_centres(phantoms):
    mech, ph = phantoms["volunteer"]
    for lk in mech.params.links[3:]:
        d = np.linalg.norm(ph.femur.vertices - lk.femur, axis=1)
        on = np.abs(d - lk.femur_radius) < 0.05
        assert on.sum() > 100  # a large part of the condyle sphere survives the union
        assert lk.tibia_radius == pytest.approx(lk.length + lk.femur_radius if lk.tibia_surface == "concave"
                                                else lk.length - lk.femur_radius)
        dt = np.linalg.norm(ph.tibia.vertices - lk.tibia, axis=1)
        assert (np.abs(dt - lk.tibia_radius) < 0.05).sum() > 30  # the facet is a cap of that sphere


@pytest.mark.parametrize("name", ["volunteer", "generic"])
def test_femur_touches_tibia_along_the_motion(phantoms, name):
    mech, ph = phantoms[name]
    for deg in (0, 30, 60, 90):
        tf, pf, _ = mech.solve(np.radians(deg))
        bones = posed_bones(ph, tf, pf)
        d = _signed_distance(bones["tibia"], bones["femur"].vertices)
        # touching: no gap and no penetration beyond the mesh resolution (mm)
        assert abs(d.min()) < 0.1, (deg, d.min())


def test_patella_rides_on_the_trochlea_mid_arc(phantoms):
    mech, ph = phantoms["volunteer"]
    for deg in (30, 55, 70):
        tf, pf, _ = mech.solve(np.radians(deg))
        bones = posed_bones(ph, tf, pf)
        d = _signed_distance(bones["femur"], bones["patella"].vertices)
        assert -1.0 < d.min() < 1.0
