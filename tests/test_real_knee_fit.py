"""The lenhart2015 knee as a subject folder (knee.fitting.reference_data.lenhart_subject): its motion read
from the dynamic-MRI table in the anatomical frames, articular regions computed from its cartilage, and the
imaging-only first estimate. Skipped without ../shared/data."""

import math

import numpy as np
import pytest

from knee.fitting.pipeline import Geometry, align_mri, anatomical_frames, contact_spheres, first_estimate
from knee.fitting.reference_data import lenhart_subject
from knee.fitting.subject import load_subject


@pytest.fixture(scope="module")
def lenhart(shared_data, tmp_path_factory):
    return load_subject(lenhart_subject(shared_data, tmp_path_factory.mktemp("lenhart") / "subject"))


def test_the_motion_in_the_anatomical_frames(lenhart):
    """60 rows of a passive flexion-extension cycle over 10-47 deg (the data's README, measured in the
    bodies' own frames), with PF motion; the CT at row 0 means row 0 is the CT's own pose."""
    flex = np.degrees(lenhart.motion.tf[:, 0])
    assert lenhart.has_pf and len(flex) == 60
    assert 8.0 < flex.min() < 13.0 and 44.0 < flex.max() < 50.0
    assert lenhart.motion.pf is not None and np.all(np.isfinite(lenhart.motion.pf))


def test_regions_from_the_cartilage_give_anatomical_fits(lenhart):
    geo = Geometry(anatomical_frames(lenhart), align_mri(lenhart))
    # the MRI is another row of the same table: the fiducials align it to the CT to well under a mm
    for b, a in geo.alignment.items():
        assert max(a.fre.values()) < 0.5, (b, a.fre)
    c = contact_spheres(lenhart, geo)
    lat, med = c["lateral"].femur, c["medial"].femur
    for s in (lat, med):
        assert 12.0 < s.radius < 35.0 and s.rms < 2.0, s
    assert lat.centre[2] > 10.0 and med.centre[2] < -10.0  # lateral and medial of the notch
    assert 30.0 < lat.centre[2] - med.centre[2] < 60.0
    fe, info = first_estimate(lenhart)
    n = info.axis.n
    assert math.degrees(math.acos(abs(n[2]))) < 30.0  # the helical axis runs medio-laterally
    assert info.axis.lateral.radius > 10.0 and info.axis.medial.radius > 10.0


def test_regions_missing_from_the_folder_are_computed_from_the_mri_surfaces(lenhart, tmp_path):
    """Without the folder's articular regions, the subject computes them from its MRI surfaces (bone and
    cartilage) in the CT landmarks' frames carried into MRI space: the contact spheres come out close to
    those of the regions computed from the cartilage alone."""
    import shutil

    d = tmp_path / "s"
    shutil.copytree(lenhart.root, d)
    for f in list((d / "mri/areas").glob("*_condyle.mrk.json")) + list((d / "mri/areas").glob("*_facet.mrk.json")):
        f.unlink()
    s2 = load_subject(d)
    assert s2.area("femur_lateral_condyle").source.startswith("computed from")
    geo1 = Geometry(anatomical_frames(lenhart), align_mri(lenhart))
    geo2 = Geometry(anatomical_frames(s2), align_mri(s2))
    c1, c2 = contact_spheres(lenhart, geo1), contact_spheres(s2, geo2)
    for side in ("lateral", "medial"):
        assert np.linalg.norm(c2[side].femur.centre - c1[side].femur.centre) < 8.0
        assert abs(c2[side].femur.radius - c1[side].femur.radius) < 8.0
    # the user's regions win when given
    assert lenhart.area("femur_lateral_condyle").source.endswith("femur_lateral_condyle.mrk.json")
