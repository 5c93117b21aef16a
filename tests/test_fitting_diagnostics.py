"""What a fit determines (knee.fitting.diagnostics): confidence intervals against the closed form of
linear least squares, invisible directions, bounds used, and the fit report's sections."""

import math

import numpy as np
import pytest

from knee.fitting.diagnostics import diagnose
from knee.fitting.optimize import TFFit, synthetic_motion
from knee.fitting.pf import PFFit
from knee.models.mechanism.params import load_model


def test_confidence_intervals_match_linear_least_squares():
    """For r = J x - y the Gauss-Newton covariance is s^2 (J^T J)^-1 with s^2 = r.r / (m - p): computed here
    independently with a plain inverse."""
    rng = np.random.default_rng(0)
    J = rng.normal(size=(40, 4)) * np.array([1.0, 3.0, 0.5, 2.0])
    y = rng.normal(size=40)
    x = np.linalg.lstsq(J, y, rcond=None)[0]
    r = J @ x - y
    d = diagnose("tf", list("abcd"), ["mm"] * 4, J, r, [0.1, 0.5, 0.96, 1.0])
    s2 = r @ r / (40 - 4)
    np.testing.assert_allclose(d.ci95, 1.96 * np.sqrt(np.diag(s2 * np.linalg.inv(J.T @ J))), rtol=1e-10)
    np.testing.assert_allclose(d.singular_values, np.linalg.svd(J, compute_uv=False), rtol=1e-12)
    assert d.condition == pytest.approx(np.linalg.cond(J)) and d.rank == 4 and d.dof == 36
    assert [n for n, _ in d.on_bound] == ["c", "d"]


def test_a_direction_the_data_cannot_see_is_named_and_not_given_a_finite_interval():
    """Two parameters that enter only through their sum: their difference is invisible; a third is fine."""
    rng = np.random.default_rng(1)
    a, c = rng.normal(size=30), rng.normal(size=30)
    J = np.column_stack([a, a, c])
    d = diagnose("pf", ["u", "v", "w"], ["mm"] * 3, J, rng.normal(size=30) * 0.1, [0, 0, 0])
    assert d.rank == 2 and math.isinf(d.condition) or d.condition > 1e12
    assert math.isinf(d.ci95[0]) and math.isinf(d.ci95[1]) and math.isfinite(d.ci95[2])
    weakest = d.weak[0]
    assert "u" in weakest and "v" in weakest and ("+0.71 u" in weakest) != ("+0.71 v" in weakest)
    assert d.as_dict()["ci95"]["u"]["half_width"] is None


def test_bound_use_of_the_tf_and_pf_variables():
    p = load_model("volunteer")
    motion, _ = synthetic_motion(p, np.linspace(0, 100, 15), noise=False)
    prob = TFFit(p, motion)
    w = np.zeros(35)
    assert np.all(prob.diagnostics(w).bound_use == 0.0)
    w[0:3] = [3.0, 4.0, 0.0]  # |w| = 5: tanh(5) of the 2 mm ball
    w[30] = 0.5
    d = prob.diagnostics(w)
    assert d.bound_use[:3] == pytest.approx([math.tanh(5.0)] * 3) and d.bound_use[30] == pytest.approx(math.tanh(0.5))
    assert d.names[:3] == ["acl.femur.x", "acl.femur.y", "acl.femur.z"] and d.names[30] == "acl.length"
    # at the true parameters with noise-free data the residuals vanish: every direction seen is exact
    assert d.residual_rms > 0 and prob.diagnostics(np.zeros(35)).residual_rms < 1e-6
    pf = PFFit(p, motion)
    dp = pf.diagnostics(np.zeros(17))
    assert dp.units[:2] == ["deg", "deg"] and dp.rank == 17 and np.all(dp.bound_use == 0.0)
    # the physical Jacobian's columns against finite differences of the residuals in physical units: a
    # small w moves a 2 mm ball's endpoint by 2 w mm, tilts a 5 deg cone's axis by atan(tan(5 deg) w)
    eps = 1e-5
    for prob_, k, per_unit in ((prob, 0, 2.0), (prob, 31, 5.0), (pf, 0, math.degrees(math.tan(math.radians(5.0)))),
                               (pf, 8, 2.0)):
        n = prob_.n_var if hasattr(prob_, "n_var") else 35
        e = np.zeros(n)
        e[k] = eps
        fd = (prob_.residuals(e) - prob_.residuals(-e)) / (2 * eps * per_unit)
        col = prob_.diagnostics(np.zeros(n)).jacobian[:, k]
        np.testing.assert_allclose(col, fd, atol=1e-5 * max(1.0, np.abs(fd).max()))


def test_bounds_per_group_move_the_parameters_that_far():
    """FitBounds reaches the fitting problems: a saturated variable moves its parameter by the bound."""
    from knee.fitting.optimize import FitBounds
    from knee.models.mechanism.params import PF_POINT_FEMUR, PF_TENDON_LENGTH

    p = load_model("volunteer")
    motion, _ = synthetic_motion(p, np.linspace(0, 100, 15), noise=False)
    w = np.zeros(17)
    w[2] = 40.0  # the femoral axis point's x, saturated
    w[14] = -40.0  # the tendon length, saturated low
    for b in (FitBounds(), FitBounds().updated({"pf_axis_point_mm": 20.0, "pf_length_mm": 12.0}, "test")):
        v = PFFit(p, motion, bounds=b).params_vector(w)
        assert v[PF_POINT_FEMUR.start] - p.to_vector()[PF_POINT_FEMUR.start] == pytest.approx(b.pf_axis_point_mm)
        assert v[PF_TENDON_LENGTH] - p.to_vector()[PF_TENDON_LENGTH] == pytest.approx(-b.pf_length_mm)
    wide = TFFit(p, motion, radius=8.0)
    wt = np.zeros(35)
    wt[0] = 40.0
    assert wide.params_vector(wt)[0] - p.to_vector()[0] == pytest.approx(8.0)
    with pytest.raises(ValueError, match="unknown bound 'radius'"):
        FitBounds().updated({"radius": 3.0}, "here")


def test_a_candidate_must_assemble_over_the_range_asked_for_beyond_the_measured_arc():
    """Measured over 10-47 deg only, the volunteer (which assembles from -104 to 129 deg) is a valid
    candidate for 0-120 deg and is rejected for 0-140 or -110-40 deg; its residuals at the measured angles do
    not depend on the option."""
    p = load_model("volunteer")
    motion, _ = synthetic_motion(p, np.linspace(10, 47, 20), noise=False)
    w = np.zeros(35)
    plain = TFFit(p, motion)
    assert plain.model_motion(w)[1]
    for rng, ok in (((0.0, 120.0), True), ((0.0, 140.0), False), ((-110.0, 40.0), False), ((-100.0, 128.0), True)):
        prob = TFFit(p, motion, assemble_over_deg=rng)
        tf, good = prob.model_motion(w)
        assert good == ok, rng
        if ok:
            np.testing.assert_allclose(prob.residuals(w), plain.residuals(w), atol=1e-12)


def test_noise_levels_set_the_component_weights():
    from knee.fitting.optimize import NOISE_SD, noise_sd, noise_weights
    from knee.fitting.pf import pf_noise_weights

    sd = noise_sd({"out_of_plane_deg": 1.0, "sagittal_deg": 0.25}, "here")
    assert sd["sagittal_mm"] == NOISE_SD["sagittal_mm"]
    np.testing.assert_allclose(noise_weights(sd), [0.5, 0.5, 1.0, 1.0, 0.5 / 1.5])
    np.testing.assert_allclose(pf_noise_weights(sd)[:3], [2.0, 0.5, 0.5])
    with pytest.raises(ValueError, match="unknown noise level 'flexion'"):
        noise_sd({"flexion": 1.0}, "here")


def test_the_cycle_halves_are_averaged_on_the_flexion_both_cover():
    from knee.fitting.optimize import Motion, average_cycle_halves

    p = load_model("volunteer")
    up, _ = synthetic_motion(p, np.linspace(5, 60, 23), noise=False)
    down, _ = synthetic_motion(p, np.linspace(60, 0, 31), noise=False)
    tf = np.vstack([up.tf, down.tf[1:]])
    pf = np.vstack([up.pf, down.pf[1:]])
    tf_h, pf_h = tf.copy(), pf.copy()
    n_up = len(up.tf)
    tf_h[:n_up, 1] -= math.radians(1.0)  # hysteresis: the flexion half 1 deg below, the extension half above
    tf_h[n_up:, 1] += math.radians(1.0)
    pf_h[:n_up, 0] += math.radians(2.0)
    pf_h[n_up:, 0] -= math.radians(2.0)
    m = average_cycle_halves(Motion(tf_h, pf_h))
    assert math.degrees(m.flexion[0]) == pytest.approx(5.0) and math.degrees(m.flexion[-1]) == pytest.approx(60.0)
    truth, _ = synthetic_motion(p, np.degrees(m.flexion), noise=False)
    # the offsets cancel (to the interpolation error) below the last 2.5 deg, where the peak row, shared by
    # both halves, carries the flexion half's offset into the extension half's interpolation
    inner = np.degrees(m.flexion) < 57.5
    np.testing.assert_allclose(m.tf[inner, 1], truth.tf[inner, 1], atol=2e-4)
    np.testing.assert_allclose(m.pf[inner, 0], truth.pf[inner, 0], atol=2e-4)
    with pytest.raises(ValueError, match="halves"):
        average_cycle_halves(up)  # no extension half


def test_a_trial_that_starts_mid_range_and_turns_twice_is_averaged_over_its_whole_range():
    """A trial like a dynamic-MRI one: it starts at 30 deg, flexes to 60, extends to 5 (past its start) and
    flexes again to 35, with a hysteresis offset of opposite sign in the flexing and extending phases and
    a 1.4 deg reversal of the flexion inside a phase. The phases are found at the true turning rows, the
    small reversal does not split a phase, and the mean cancels the offsets over 5-60 deg: every flexing
    frame is used, not only those of the first phase (which alone covers only 30-60 deg)."""
    from knee.fitting.optimize import Motion, average_cycle_halves, cycle_phases

    p = load_model("volunteer")
    legs = [np.linspace(30, 60, 16), np.linspace(60, 5, 28)[1:], np.linspace(5, 35, 16)[1:]]
    angles = np.concatenate(legs)
    angles[30] += 3.5  # the flexion turns back inside the extending phase, by less than turn_deg (3 deg)
    assert 1.0 < angles[30] - angles[29] < 3.0
    m, _ = synthetic_motion(p, angles, noise=False)
    turns = [0, 15, 15 + 27, len(angles) - 1]
    assert [(s, e) for s, e, _ in cycle_phases(m.flexion)] == list(zip(turns[:-1], turns[1:]))
    assert [d for *_, d in cycle_phases(m.flexion)] == [1, -1, 1]
    sign = np.ones(len(angles))
    sign[turns[1] + 1:turns[2]] = -1.0  # the extending phase's frames (the turning rows stay flexing)
    tf, pf = m.tf.copy(), m.pf.copy()
    tf[:, 1] -= math.radians(1.0) * sign
    pf[:, 0] += math.radians(2.0) * sign
    mean = average_cycle_halves(Motion(tf, pf))
    assert math.degrees(mean.flexion[0]) == pytest.approx(5.0) and math.degrees(mean.flexion[-1]) > 59.0
    truth, _ = synthetic_motion(p, np.degrees(mean.flexion), noise=False)
    # the turning rows carry the flexing phases' offset into the extending phase's interpolation, and the
    # reversal's rows are interpolated from both sides: away from them the offsets cancel
    deg = np.degrees(mean.flexion)
    clean = (deg > 7.5) & (deg < 57.5) & (np.abs(deg - angles[30]) > 3.0)
    np.testing.assert_allclose(mean.tf[clean, 1], truth.tf[clean, 1], atol=3e-4)
    np.testing.assert_allclose(mean.pf[clean, 0], truth.pf[clean, 0], atol=3e-4)
    # without the last phase the flexing frames cover only 30-60 deg, and so does the mean
    first_two = average_cycle_halves(Motion(tf[:turns[2] + 1], pf[:turns[2] + 1]))
    assert math.degrees(first_two.flexion[0]) == pytest.approx(30.0)
    # a trial that turns back by 4 deg only: an extending phase under 5 deg is refused, naming what it covers
    short, _ = synthetic_motion(p, np.concatenate([np.linspace(10, 60, 20), [58.0, 56.0]]), noise=False)
    with pytest.raises(ValueError, match=r"cover 5 deg or more .*extension 56.0-60.0 deg"):
        average_cycle_halves(short)


def test_a_fit_to_the_phases_mean_reports_its_errors_against_every_frame_too(tmp_path):
    """The synthetic knee's motion as a cycle (flex to 90, extend to 0) with +-1.5 deg of adduction
    hysteresis: fitted to the phases' mean, the model is near the truth there; against every frame as
    measured the hysteresis adds about its 1.5 deg, which no 1-DoF model can follow."""
    from knee.fitting.pipeline import fit_subject
    from knee.fitting.synthetic import make_subject
    from knee.foundations.imaging import write_motion_csv

    d = make_subject(tmp_path / "s", seed=0, frames=20)
    truth = load_model(d / "truth.toml")
    up, down = np.linspace(0, 90, 16), np.linspace(90, 0, 16)[1:]
    m, _ = synthetic_motion(truth, np.concatenate([up, down]), noise=False)
    tf = m.tf.copy()
    tf[:16, 1] -= math.radians(1.5)
    tf[16:, 1] += math.radians(1.5)
    write_motion_csv(d / "motion.csv", tf, m.pf)
    o = fit_subject(d, effort="quick", average_halves=True)
    assert o.fitted_errors.tf.mae[1] < 0.5
    assert 1.2 < o.as_measured_errors.tf.mae[1] < 2.0
    assert len(o.as_measured_errors.model_tf) == 31 and len(o.motion.tf) == 91  # the mean on a 1 deg grid


def test_trials_fitted_together_and_a_held_out_trial_checked(tmp_path):
    """A second trial of the synthetic knee (other noise) fitted together doubles the frames; a third, held
    out, is reported with errors of the measurement noise's size."""
    from knee.fitting.pipeline import fit_subject
    from knee.fitting.synthetic import make_subject
    from knee.foundations.imaging import write_motion_csv

    d = make_subject(tmp_path / "s", seed=0, frames=20)
    truth = load_model(d / "truth.toml")
    trials = []
    for k in (7, 8):
        m, _ = synthetic_motion(truth, np.linspace(0, 120, 20), noise=True, seed=k)
        trials.append(write_motion_csv(tmp_path / f"trial{k}.csv", m.tf, m.pf))
    o = fit_subject(d, effort="quick", extra_trials=[trials[0]], check_trials=[trials[1]])
    assert len(o.motion.tf) == 40
    (name, v), = o.cross_trial
    assert name.endswith("trial8.csv")
    assert np.all(v.tf.mae[1:] < 2.0 * o.fitted_errors.tf.mae[1:] + 0.5), (v.tf.mae, o.fitted_errors.tf.mae)


def test_the_motions_helical_axis_is_the_mechanisms_own():
    """Noise-free PF motion of a parameter set: its mean helical axis is the set's helical axis (direction,
    point on z = 0) and its pitch the set's lambda1."""
    from knee.fitting.pipeline import motion_helical_axis

    p = load_model("volunteer")
    m, _ = synthetic_motion(p, np.linspace(0, 110, 40), noise=False)
    ax = motion_helical_axis(m.pf)
    n0 = p.pf.axis_femur / np.linalg.norm(p.pf.axis_femur)
    n0 = n0 if n0[2] > 0 else -n0
    q0 = p.pf.point_femur - p.pf.point_femur[2] / n0[2] * n0
    assert math.degrees(math.acos(min(1.0, ax.n @ n0))) < 1e-4
    np.testing.assert_allclose(ax.q, q0, atol=1e-4)
    assert ax.lambda1 == pytest.approx(p.pf.lambda1 * np.sign(p.pf.axis_femur[2]), abs=1e-4)
    assert ax.span_deg > 10.0
    short, _ = synthetic_motion(p, np.linspace(20, 24, 5), noise=False)
    assert motion_helical_axis(short.pf) is None  # under MIN_AXIS_SPAN_DEG of patellar rotation
