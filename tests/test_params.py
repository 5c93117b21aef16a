"""Parameter sets and the TOML format: Table 1 values, round trips, bad files."""

import math

import numpy as np
import pytest

from knee.models.mechanism.params import (
    N_PARAMS,
    ModelFileError,
    UnknownModelError,
    bundled_models,
    dumps_toml,
    load_model,
    load_toml,
    parameter_names,
    save_toml,
)

VOLUNTEER = load_model("volunteer").to_toml()


def test_bundled_names():
    assert {"volunteer", "volunteer-initial", "generic-sancisi2017"} <= set(bundled_models())


def test_volunteer_is_table_1_optimised():
    p = load_model("volunteer")
    acl = p.link("acl")
    np.testing.assert_allclose(acl.tibia, [14.03, -1.21, -3.72])
    np.testing.assert_allclose(acl.femur, [-8.60, -1.43, 7.28])
    assert [lk.length for lk in p.links] == [33.05, 41.46, 100.79, 78.77, 31.11]
    # n = [cos(phi) sin(theta), sin(phi) sin(theta), cos(theta)] with theta=0.14, phi=-0.24
    th, ph = 0.14, -0.24
    np.testing.assert_allclose(p.pf.axis_femur, [math.cos(ph) * math.sin(th), math.sin(ph) * math.sin(th),
                                                 math.cos(th)], atol=1e-15)
    np.testing.assert_allclose(p.pf.point_patella, [-45.02, 5.55, 0.0])
    assert (p.pf.lambda0, p.pf.lambda1, p.pf.tendon_length) == (1.48, -0.78, 80.48)
    assert p.pf.reference_flexion == pytest.approx(math.radians(55))
    q = load_model("volunteer-initial")
    assert [lk.length for lk in q.links] == [32.85, 39.65, 102.33, 80.72, 30.19]
    assert q.pf.lambda1 == -0.07


def test_generic_has_sphere_plane_contacts_and_a_citation():
    p = load_model("generic-sancisi2017")
    assert p.kinds[3:] == ("sphere-plane", "sphere-plane")
    assert "Meccanica" in p.source and p.pf is None
    assert abs(np.linalg.norm(p.link("mc").normal) - 1) < 1e-12


@pytest.mark.parametrize("name", ["volunteer", "volunteer-initial", "generic-sancisi2017"])
def test_toml_round_trip(name, tmp_path):
    p = load_model(name)
    path = save_toml(p, tmp_path / "m.toml")
    q = load_toml(path)
    assert np.array_equal(p.to_vector(), q.to_vector())
    assert q.kinds == p.kinds and q.name == p.name
    assert np.array_equal(p.with_vector(p.to_vector()).to_vector(), p.to_vector())
    with pytest.raises(ModelFileError, match="not overwritten"):
        save_toml(p, path)


def test_parameter_names_cover_the_vector():
    names = parameter_names()
    assert len(names) == N_PARAMS == len(set(names))
    assert names[9] == "link0.length" and names[-1] == "pf.reference_flexion"


def _write(tmp_path, text):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    return f


@pytest.mark.parametrize("edit, match", [
    (("length = 33.05\n", ""), r"tf.links\[0\] \(acl\): missing field 'length'"),
    (("length = 41.46", "length = nan"), r"pcl\): field 'length' is not finite"),
    (("femur = [-7.25, -2.9, -38.05]", "femur = [-7.25, inf, -38.05]"), r"mcl\): field 'femur' has a non-finite"),
    (('length = "mm"', 'length = "m"'), r"\[units\]: length must be \"mm\""),
    (('kind = "distance"', 'kind = "hinge"'), r"field 'kind' must be one of distance, sphere-plane"),
    (("version = 1", "version = 7"), r"field 'version' must be 1"),
    (("tendon_length = 80.48\n", ""), r"\[pf\]: missing field 'tendon_length'"),
    (("femur = [-8.6, -1.43, 7.28]", "femur = [-8.6, -1.43]"), r"field 'femur' must be a list of 3 numbers"),
])
def test_bad_files_name_the_field(tmp_path, edit, match):
    text = VOLUNTEER
    assert edit[0] in text, edit[0]
    f = _write(tmp_path, text.replace(edit[0], edit[1], 1))
    with pytest.raises(ModelFileError, match=match) as e:
        load_toml(f)
    assert "\n" not in str(e.value)
    assert isinstance(e.value, ValueError)


def test_wrong_link_count_and_unknown_model(tmp_path):
    text = VOLUNTEER
    first = text.index("[[tf.links]]")
    second = text.index("[[tf.links]]", first + 1)
    f = _write(tmp_path, text[:first] + text[second:])
    with pytest.raises(ModelFileError, match="exactly 5"):
        load_toml(f)
    with pytest.raises(UnknownModelError, match="unknown model 'nope'"):
        load_model("nope")
    with pytest.raises(ModelFileError, match="not valid TOML"):
        load_toml(_write(tmp_path, "a = = 1"))


def test_dumps_is_loadable_text():
    assert dumps_toml(load_model("generic-sancisi2017")).startswith('format = "knee-mechanism"')
