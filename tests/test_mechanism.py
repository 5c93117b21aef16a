"""The mechanism solver against independent computations (knee.models.mechanism.reference, the closure
equations evaluated directly on the poses, finite differences)."""

import math

import numpy as np
import pytest

from knee.foundations.conventions import joint_to_pose, pose_to_joint
from knee.foundations.errors import AssemblyError
from knee.models.mechanism import Mechanism, compiled, load_model
from knee.models.mechanism import reference as ref

DEG = np.radians


def test_sweep_closes_every_link(volunteer):
    res = volunteer.sweep(DEG(np.arange(0, 126)))
    assert res.complete and res.tf.shape == (126, 6)
    assert res.residual.max() < 1e-9
    p = volunteer.params
    for q in res.tf[::5]:
        # eq. 1, evaluated by the independent NumPy code
        assert np.abs(ref.tf_residuals(p, q[1:], q[0])).max() < 1e-9


def test_pf_equations_hold_on_the_poses(volunteer):
    """Eqs. 2-4 checked directly on the returned poses."""
    p = volunteer.params
    f = p.pf
    res = volunteer.sweep(DEG(np.arange(0, 126, 5)))
    Ttf, Tpf = res.tf_poses, res.pf_poses
    nf = f.axis_femur / np.linalg.norm(f.axis_femur)
    for k in range(res.flexion.size):
        R, P = Tpf[k, :3, :3], Tpf[k, :3, 3]
        np.testing.assert_allclose(R @ f.axis_patella, nf, atol=1e-12)                  # eq. 2
        d = R @ f.point_patella + P - f.point_femur                                      # eq. 3
        np.testing.assert_allclose(np.cross(d, nf), 0, atol=1e-10)
        theta = res.psi[k] - volunteer.psi_ref
        assert d @ nf == pytest.approx(f.lambda0 + f.lambda1 * theta, abs=1e-10)
        tendon = (R @ f.tendon_patella + P) - (Ttf[k, :3, :3] @ f.tendon_tibia + Ttf[k, :3, 3])
        assert np.linalg.norm(tendon) == pytest.approx(f.tendon_length, abs=1e-9)       # eq. 4


def test_pf_reference_pose(volunteer):
    """At the reference flexion theta = 0, and the patella is the anterior root."""
    a_ref = volunteer.params.pf.reference_flexion
    tf, pf, _ = volunteer.solve(a_ref)
    res = volunteer.sweep([a_ref])
    assert res.psi[0] == pytest.approx(volunteer.psi_ref, abs=1e-10)
    grid = np.linspace(-np.pi, np.pi, 2001)
    vals = np.array([ref.tendon_residual(volunteer.params, s, 0.0, tf[1:], a_ref) for s in grid])
    roots = grid[np.nonzero(np.sign(vals[:-1]) != np.sign(vals[1:]))[0]]
    assert len(roots) >= 2
    anterior = [ref.pf_pose(volunteer.params, r, 0.0)[1][0] for r in roots]
    assert pf[3] == pytest.approx(max(anterior), abs=0.5)
    assert pf[3] > 20  # in front of the femur


def test_sweep_matches_independent_least_squares(volunteer):
    al = DEG(np.arange(0, 121, 4))
    res = volunteer.sweep(al)
    tf, pf = ref.solve_sweep_least_squares(volunteer.params, al, res.tf[0, 1:], volunteer.psi_ref, res.psi[0])
    np.testing.assert_allclose(res.tf, tf, atol=1e-8)
    np.testing.assert_allclose(res.pf, pf, atol=1e-8)


def test_sphere_plane_variant(generic):
    res = generic.sweep(DEG(np.arange(0, 101, 5)))
    assert res.complete and res.residual.max() < 1e-9
    assert np.all(np.isnan(res.pf))
    p = generic.params
    for q in res.tf:
        R, P = joint_to_pose(q)[:3, :3], q[3:]
        for lk in p.links[3:]:
            n = lk.normal / np.linalg.norm(lk.normal)
            dist = n @ (R.T @ (lk.femur - P) - lk.tibia)   # sphere centre to tibial plane
            assert dist == pytest.approx(lk.length, abs=1e-9)
    # near the anatomical pose at extension: tibia origin close to the femur's knee centre
    assert np.abs(res.tf[0, 3:]).max() < 2.0 and abs(res.tf[0, 1]) < DEG(2)


def test_assembly_ranges(volunteer):
    lo, hi = np.degrees(volunteer.assembly_range)
    assert lo < 0 and hi >= 125.0
    ini = Mechanism.from_name("volunteer-initial")
    lo_i, hi_i = np.degrees(ini.assembly_range)
    assert 0 < lo_i < hi_i < 125  # the first estimate does not assemble at full extension
    # the ends are real: just inside closes, just outside does not
    for a in (hi - 1e-3, lo + 1e-3):
        volunteer.solve(DEG(a))
    with pytest.raises(AssemblyError, match="outside the assembly range"):
        volunteer.solve(DEG(hi + 0.01))


def test_sweep_stops_early_and_reports(volunteer):
    res = volunteer.sweep(DEG(np.arange(110, 141, 2.0)))
    assert res.status == "no-convergence" and not res.complete
    hi = np.degrees(volunteer.assembly_range[1])
    assert res.flexion.size == np.sum(np.arange(110, 141, 2.0) <= hi)
    assert np.degrees(res.limit) == pytest.approx(hi, abs=1e-3)
    assert "stops assembling at" in res.message and "\n" not in res.message
    assert res.residual.max() < 1e-9
    out = volunteer.sweep(DEG([140.0, 141.0]))
    assert out.status == "out-of-range" and out.flexion.size == 0


def test_descending_and_coarse_sweeps_stay_on_the_branch(volunteer):
    fine = volunteer.sweep(DEG(np.arange(0, 121, 1.0)))
    down = volunteer.sweep(DEG(np.arange(120, -1, -10.0)))
    assert down.complete
    np.testing.assert_allclose(down.tf[::-1], fine.tf[::10], atol=1e-9)
    np.testing.assert_allclose(down.pf[::-1], fine.pf[::10], atol=1e-9)


def test_sweeps_from_an_end_of_the_range_stay_on_the_branch(volunteer):
    """Both branches meet at the ends of the assembly range; a sweep that starts exactly there used to
    continue onto the other branch (up to 2 mm off at 45 deg). Every row must equal the single solve."""
    lo, hi = volunteer.assembly_range
    for first in (lo, hi):
        res = volunteer.sweep(np.array([first, DEG(45.0), DEG(60.0)]))
        assert res.complete
        for k, a in enumerate(res.flexion):
            np.testing.assert_allclose(res.tf[k], volunteer.solve(a)[0], atol=1e-8)


def test_single_solve_equals_sweep(volunteer):
    res = volunteer.sweep(DEG([17.0, 63.5, 101.0]))
    for k, a in enumerate(res.flexion):
        tf, pf, r = volunteer.solve(a)
        np.testing.assert_allclose(tf, res.tf[k], atol=1e-10)
        np.testing.assert_allclose(pf, res.pf[k], atol=1e-10)
        assert r < 1e-9


def test_assembly_modes(volunteer):
    a = DEG(30.0)
    modes = volunteer.assembly_modes(a, n_starts=600)
    assert len(modes) >= 2
    on_branch = volunteer.solve(a)[0][1:]
    np.testing.assert_allclose(modes[0], on_branch, atol=1e-6)
    for m in modes:
        assert np.abs(ref.tf_residuals(volunteer.params, m, a)).max() < 1e-9
    for i in range(len(modes)):
        for j in range(i):
            assert np.abs(modes[i] - modes[j]).max() > 1e-6


def test_jacobian_condition_reported(volunteer):
    res = volunteer.sweep(DEG(np.arange(0, 130)))
    assert res.condition.shape == (130,) and np.all(res.condition >= 1)
    # towards the fold at the end of the range the Jacobian degenerates
    near = volunteer.sweep(DEG([np.degrees(volunteer.assembly_range[1]) - 1e-4]))
    assert near.condition[0] > 10 * np.median(res.condition)
    J = res.jacobian[40]
    assert res.condition[40] == pytest.approx(np.linalg.cond(J), rel=1e-9)


def _fd(mech_params, al, k, h):
    """Central difference of the sweep with respect to parameter k."""
    out = []
    for s in (1, -1):
        v = mech_params.to_vector()
        v[k] += s * h
        m = Mechanism(mech_params.with_vector(v))
        r = m.sweep(al)
        out.append(np.column_stack([r.tf, r.pf]))
    return (out[0] - out[1]) / (2 * h)


@pytest.mark.parametrize("k", [2, 9, 13, 39, 49, 54, 62, 68, 69, 70, 71])
def test_parameter_derivatives_match_finite_differences(volunteer, k):
    al = DEG(np.array([20.0, 70.0, 110.0]))
    sens = volunteer.sensitivities(al)
    h = 1e-5 if k != 71 else 1e-6
    fd = _fd(volunteer.params, al, k, h)
    assert np.abs(fd).max() > 1e-3  # the parameter moves the motion: the comparison is not 0 == 0
    np.testing.assert_allclose(sens.d_params[:, :, k], fd, atol=2e-5, rtol=1e-4)


def test_flexion_derivative_matches_finite_differences(volunteer, generic):
    for m in (volunteer, generic):
        al = DEG(np.array([10.0, 50.0, 95.0]))
        h = 1e-6
        up, dn = m.sweep(al + h), m.sweep(al - h)
        fd = (np.column_stack([up.tf, up.pf]) - np.column_stack([dn.tf, dn.pf])) / (2 * h)
        sens = m.sensitivities(al)
        k = sens.d_flexion.shape[1]
        np.testing.assert_allclose(sens.d_flexion, fd[:, :k], atol=1e-5)
        assert np.allclose(sens.d_flexion[:, 0], 1.0)


def test_compiled_and_casadi_fallback_agree(tmp_path, monkeypatch):
    monkeypatch.setenv("KNEE_CACHE_DIR", str(tmp_path))
    p = load_model("volunteer")
    b = compiled.new_backend(p.kinds, p.has_pf, compile=True)
    assert b.compiled and b.library.parent == tmp_path and b.library.is_file()
    again = compiled.new_backend(p.kinds, p.has_pf, compile=True)  # from the on-disk cache
    assert again.library == b.library
    fast = Mechanism(p, compile=True)
    slow = Mechanism(p, compile=False)
    assert fast.compiled and not slow.compiled
    al = DEG(np.arange(0, 121, 3.0))
    a, b2 = fast.sweep(al), slow.sweep(al)
    np.testing.assert_allclose(a.tf, b2.tf, atol=1e-10)
    np.testing.assert_allclose(a.pf, b2.pf, atol=1e-10)
    assert fast.assembly_range == pytest.approx(slow.assembly_range, abs=1e-8)


def test_two_mechanisms_of_one_structure_in_two_threads(volunteer):
    """Each thread solves with its own buffers: two mechanisms of one structure swept concurrently, many
    times, give exactly what each gives alone (shared buffers would mix their parameters and states)."""
    import threading

    from knee.fitting.optimize import perturb_endpoints

    other = Mechanism(perturb_endpoints(volunteer.params, 1.0, 2.0, seed=3))
    al = DEG(np.arange(0, 100, 1.0))
    expected = {id(m): m.sweep(al).tf for m in (volunteer, other)}
    bad = []

    def work(m):
        for _ in range(40):
            if not np.array_equal(m.sweep(al).tf, expected[id(m)]):
                bad.append(m.params.name)

    threads = [threading.Thread(target=work, args=(m,)) for m in (volunteer, other, volunteer, other)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not bad
    assert not np.allclose(expected[id(volunteer)], expected[id(other)])


def test_no_compiler_falls_back(monkeypatch, tmp_path):
    monkeypatch.setenv("KNEE_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(compiled, "find_compiler", lambda: None)
    p = load_model("generic-sancisi2017")
    b = compiled.new_backend(p.kinds, p.has_pf, compile=True)
    assert not b.compiled and b.library is None
    assert not list(tmp_path.iterdir())


def test_bad_angles(volunteer):
    with pytest.raises(ValueError, match="finite"):
        volunteer.sweep([0.0, math.nan])
    with pytest.raises(ValueError, match="at least one"):
        volunteer.sweep([])


def test_stored_initial_pose_is_the_multistart_branch(volunteer):
    from dataclasses import replace

    p = load_model("volunteer")
    assert p.initial is not None
    searched = Mechanism(replace(p, initial=None))
    al = DEG(np.arange(0, 121, 10.0))
    np.testing.assert_allclose(searched.sweep(al).tf, volunteer.sweep(al).tf, atol=1e-9)
    assert searched.assembly_range == pytest.approx(volunteer.assembly_range, abs=1e-8)


def test_jump_detector_on_synthetic_paths():
    from knee.models.mechanism.solver import detect_jumps

    a = DEG(np.arange(1.0, 21.0))
    x = np.column_stack([0.01 * a, -0.2 + 0.05 * a, 0.3 * np.degrees(a), -27 + 0.0 * a, 0.1 * np.degrees(a)])
    x0 = np.array([0.0, -0.2, 0.0, -27.0, 0.0])
    assert not detect_jumps(x0, 0.0, x, a).any()
    y = x.copy()
    y[12:, 4] += 5.0  # the lateral translation jumps by 5 mm between 12 and 13 deg: another branch
    flags = detect_jumps(x0, 0.0, y, a)
    assert flags.tolist() == [k == 12 for k in range(20)]
    z = x.copy()
    z[:, 0] += DEG(0.01) * np.arange(20) ** 2  # fast but smooth (towards a fold): not a jump
    assert not detect_jumps(x0, 0.0, z, a).any()


def test_sweeps_on_the_two_branches_never_mix(volunteer):
    """The other root at each angle is a different branch: continuation from the default branch never
    reaches it, at any step size up to 10 degrees."""
    al = DEG(np.arange(0.0, 121.0, 10.0))
    res = volunteer.sweep(al)
    for k, a in enumerate(al):
        modes = volunteer.assembly_modes(a, n_starts=400)
        others = [m for m in modes if np.abs(m - res.tf[k, 1:]).max() > 1e-6]
        assert others, "expected the second branch"
        assert min(np.abs(m - res.tf[k, 1:]).max() for m in others) > 1e-3


@pytest.mark.parametrize("name,deg", [("volunteer", 90.0), ("volunteer", 120.0), ("generic-sancisi2017", 120.0)])
def test_assembly_modes_belong_to_the_requested_flexion(name, deg):
    """Multi-start Newton can converge past |beta| = 90 deg, to a pose whose joint coordinates are those of
    flexion alpha +- 180 deg (found at these angles with 2000 starts): such poses are not modes at alpha."""
    m = Mechanism.from_name(name)
    a = DEG(deg)
    modes = m.assembly_modes(a, n_starts=2000)
    assert bool(modes) == m.in_range(a)  # generic-sancisi2017 has no pose at 120 deg: only the spurious ones
    if not modes:
        return
    q = np.column_stack([np.full(len(modes), a), np.array(modes)])
    back = pose_to_joint(joint_to_pose(q))
    np.testing.assert_allclose(back, q, atol=1e-9)
    for mode in modes:
        assert np.abs(ref.tf_residuals(m.params, mode, a)).max() < 1e-9


def test_the_solver_cache_loads_only_what_it_can_trust(tmp_path, monkeypatch):
    """A cached library is loaded only from a folder no one else can write to and only when it matches the
    SHA-256 recorded when it was compiled: a corrupt one is compiled again, a shared folder not used."""
    import hashlib

    cache = tmp_path / "cache"
    monkeypatch.setenv("KNEE_CACHE_DIR", str(cache))
    p = load_model("volunteer")
    b = compiled.new_backend(p.kinds, p.has_pf, compile=True)
    assert b.library.parent == cache and (cache.stat().st_mode & 0o777) == 0o700
    good = b.library.read_bytes()
    assert b.library.with_name(b.library.name + ".sha256").read_text().strip() == hashlib.sha256(good).hexdigest()
    part = cache / "replacement"
    part.write_bytes(good[: len(good) // 2])
    part.replace(b.library)  # a truncated (or replaced) library (a new file: the loaded one is left alone)
    again = compiled.new_backend(p.kinds, p.has_pf, compile=True)
    assert again.library == b.library and again.library.read_bytes() == good  # compiled again, not loaded
    cache.chmod(0o777)  # a folder others can write to
    shared = compiled.new_backend(p.kinds, p.has_pf, compile=True)
    assert shared.compiled and shared.library.parent != cache
    res = Mechanism(p, compile=True).sweep(DEG(np.arange(0, 31, 5.0)))
    assert res.complete


def test_a_private_solver_cache_is_removed_when_the_process_ends(tmp_path):
    """Where the shared cache cannot be trusted the library is compiled into a private temporary folder;
    that folder goes when the process ends, so repeated runs leave nothing behind in the temp folder."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    cache = tmp_path / "cache"
    cache.mkdir()
    cache.chmod(0o777)  # others could write here: not used
    temp = tmp_path / "temp"
    temp.mkdir()
    code = ("from knee.models.mechanism import compiled, load_model; p = load_model('volunteer'); "
            "b = compiled.new_backend(p.kinds, p.has_pf, compile=True); print(b.library)")
    env = {**os.environ, "KNEE_CACHE_DIR": str(cache), "TMPDIR": str(temp)}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    lib = Path(out.stdout.strip().splitlines()[-1])
    assert lib.parent.parent == temp and lib.parent.name.startswith("knee-private-cache-")  # it was used
    assert not lib.parent.exists() and not list(temp.glob("knee-private-cache-*"))


def test_a_diverging_closure_is_said_in_words_not_as_nan():
    from dataclasses import replace

    from knee.models.mechanism.params import InitialPose
    from knee.models.mechanism.solver import _residual_text

    assert _residual_text(float("nan")).startswith("Newton diverged") and _residual_text(0.5) == "residual 0.5 mm"
    p = load_model("volunteer")
    far = replace(p, initial=InitialPose(0.0, np.array([3.0, -3.0, 500.0, -900.0, 700.0])))
    with pytest.raises(AssemblyError) as e:
        Mechanism(far)
    assert "nan" not in str(e.value)
