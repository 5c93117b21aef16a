"""Statics of the mechanism (virtual work), Hertz contact (closed form) and the elastic foundation."""

import math

import numpy as np
import pytest
from scipy.integrate import quad

from knee.foundations.conventions import joint_to_pose
from knee.foundations.errors import AssemblyError, KneeInputError
from knee.models.contact import (
    CARTILAGE,
    Cartilage,
    condyle_cap,
    effective_modulus,
    effective_radius,
    foundation,
    foundation_closed_form_approach,
    foundation_force,
    hertz,
)
from knee.models.contact import _tibial_depth as _depth
from knee.models.mechanism import Mechanism
from knee.models.statics import member_lines, solve_statics


def test_large_sweep_steps_stay_on_the_branch(volunteer):
    """A 10-degree step used to converge onto another branch silently; steps are now subdivided."""
    a = volunteer.sweep(np.radians(np.arange(0, 121, 10.0)))
    b = volunteer.sweep(np.radians(np.arange(0, 121, 1.0)))
    assert a.complete
    np.testing.assert_allclose(a.tf, b.tf[::10], atol=1e-9)


def _tibia_twist(mech, a, h=1e-6):
    """Spatial twist (omega, velocity of the point at the femur origin) of the tibia per unit flexion."""
    tf, pf = mech.motion_at(np.array([a - h, a, a + h]))
    T = joint_to_pose(tf)
    dT = (T[2] - T[0]) / (2 * h)
    W = dT[:3, :3] @ T[1, :3, :3].T
    w = np.array([W[2, 1], W[0, 2], W[1, 0]])
    return w, dT[:3, 3] - np.cross(w, T[1, :3, 3]), tf[1], pf[1], T[1]


@pytest.mark.parametrize("deg", [10.0, 45.0, 90.0])
def test_statics_satisfies_virtual_work(volunteer, deg):
    """Independent check: along the mechanism's own motion the five links do no work (constant length), so
    the tendon force must equal minus the load's power divided by the tendon's unit power."""
    a = math.radians(deg)
    F = np.array([35.0, 650.0, -40.0])
    M = np.array([2000.0, -1500.0, 5000.0])
    st = solve_statics(volunteer, a, F, M)
    w, v0, tf, pf, T = _tibia_twist(volunteer, a)
    u, b = member_lines(volunteer.params, tf[None], pf[None])
    unit_power = np.einsum("ij,ij->i", u[0], v0 + np.cross(w, b[0]))
    assert np.abs(unit_power[:5]).max() < 1e-6 * np.abs(unit_power[5])  # links: no work
    R, P = T[:3, :3], T[:3, 3]
    Fw, Mw = R @ F, R @ M + np.cross(P, R @ F)
    tendon = -(Fw @ v0 + Mw @ w) / unit_power[5]
    assert st.force("tendon")[0] == pytest.approx(tendon, rel=1e-6)
    # and the full equilibrium: sum of member wrenches + load = 0
    f = st.forces[0]
    net_f = (f[:, None] * st.directions[0]).sum(axis=0) + Fw
    net_m = (f[:, None] * np.cross(st.points[0], st.directions[0])).sum(axis=0) + Mw
    assert np.abs(net_f).max() < 1e-8 * np.linalg.norm(F) and np.abs(net_m).max() < 1e-6 * np.linalg.norm(Mw)


def test_statics_flags_members_that_cannot_carry_the_load(volunteer):
    st = solve_statics(volunteer, np.radians([0.0, 60.0]), [0.0, 700.0, 0.0])
    # a compressive load along the tibial axis: both condyles in compression at 60 deg
    assert st.force("lc")[1] < 0 and st.force("mc")[1] < 0
    flat = [x for f in st.flags for x in f]
    assert any("would have to push" in x for x in flat)
    pulled = solve_statics(volunteer, math.radians(20.0), [0.0, -700.0, 0.0])  # a distracting load
    assert any("would have to pull" in x for x in pulled.flags[0])
    slack = solve_statics(volunteer, math.radians(30.0), [-638.8, 315.2, 290.6], [25891.0, -15092.0, 33782.0])
    assert "every ligament is slack or pushing" in slack.flags[0] and not slack.ok[0]
    with pytest.raises(KneeInputError, match="patella"):
        solve_statics(Mechanism.from_name("generic-sancisi2017"), 0.3, [0, 1, 0])
    with pytest.raises(AssemblyError, match="outside the assembly range"):
        solve_statics(volunteer, math.radians(170.0), [0, 1, 0])


def test_hertz_equals_the_closed_form():
    """Johnson (1985) 4.2, computed here independently from the definitions."""
    E, nu = 8.0, 0.4
    c = Cartilage(E=E, nu=nu)
    for surface, rt in (("convex", 55.0), ("concave", 60.0), ("plane", None)):
        F = np.array([0.0, 10.0, 250.0, 1800.0])
        r = hertz(F, 24.0, rt, surface, c, c)
        inv = 1 / 24.0 + (0 if surface == "plane" else (1 / rt if surface == "convex" else -1 / rt))
        Rs = 1 / inv
        Es = E / (2 * (1 - nu ** 2))
        a = (3 * F * Rs / (4 * Es)) ** (1 / 3)
        np.testing.assert_allclose(r.radius, a, rtol=1e-12)
        np.testing.assert_allclose(r.area, np.pi * a ** 2, rtol=1e-12)
        np.testing.assert_allclose(r.peak[1:], 3 * F[1:] / (2 * np.pi * a[1:] ** 2), rtol=1e-9)
        np.testing.assert_allclose(r.mean[1:], F[1:] / (np.pi * a[1:] ** 2), rtol=1e-9)
        np.testing.assert_allclose(r.approach, a ** 2 / Rs, rtol=1e-12)
        # p0 = (6 F E*^2 / (pi^3 R*^2))^(1/3), the other textbook form
        np.testing.assert_allclose(r.peak[1:], (6 * F[1:] * Es ** 2 / (np.pi ** 3 * Rs ** 2)) ** (1 / 3), rtol=1e-9)
        assert r.area[0] == 0 and r.peak[0] == 0
    with pytest.raises(KneeInputError, match="concave"):
        effective_radius(24.0, 20.0, "concave")
    with pytest.raises(KneeInputError):
        Cartilage(nu=0.5)


@pytest.mark.parametrize("surface,rt", [("convex", 55.0), ("concave", 55.0), ("plane", None)])
def test_elastic_foundation_balances_the_load(surface, rt):
    F = 600.0
    cap = condyle_cap(24.0)
    r = foundation(F, 24.0, rt, surface, cap)
    assert r.net_force[2] == pytest.approx(F, rel=1e-8)
    assert np.hypot(*r.net_force[:2]) < 1e-6 * F  # the symmetric cap: no shear
    assert r.peak > r.mean > 0 and 0 < r.area < cap.area
    # independent: the same foundation on the smooth sphere, integrated over the polar angle (scipy quad),
    # at the approach the mesh solve found, carries the load within 1%
    K = CARTILAGE.foundation_modulus

    def integrand(th):
        x = 24.0 * np.array([np.sin(th), 0.0, -np.cos(th)])
        d, n = _depth(x[None], 24.0, rt, surface, r.approach)
        return K * max(d[0], 0.0) * n[0][2] * 2 * np.pi * 24.0 ** 2 * np.sin(th)

    total, _ = quad(integrand, 0.0, np.radians(40.0), limit=200, points=[np.sqrt(2 * r.approach * 40) / 24.0])
    assert total == pytest.approx(F, rel=0.01)
    # and in the small-contact limit the paraboloid closed form F = pi K R* delta^2 holds (2%: conforming)
    d0 = foundation_closed_form_approach(100.0, 24.0, rt, surface)
    net, p = foundation_force(cap, 24.0, rt, surface, d0)
    assert net[2] == pytest.approx(100.0, rel=0.02)


def test_foundation_modulus_is_the_confined_layers():
    """The elastic foundation's K is the confined (P-wave) modulus lambda + 2 mu of the cartilage over the
    two layers' thickness 2 h (Blankevoort et al. 1991): 4.741 N/mm^3 for E = 5 MPa, nu = 0.45, h = 2 mm."""
    E, nu, h = 5.0, 0.45, 2.0
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    assert Cartilage(E, nu, h).foundation_modulus == pytest.approx((lam + 2 * mu) / (2 * h), rel=1e-12)
    assert CARTILAGE.foundation_modulus == pytest.approx(4.7414, abs=1e-4)
    assert effective_modulus() == pytest.approx(5.0 / (2 * (1 - 0.45 ** 2)))


def test_contact_along_flexion_matches_the_closed_forms(volunteer):
    """``knee contact``'s numbers at each angle: the statics' compressive contact force, its Hertz area and
    peak pressure by the closed form written out here (Johnson 1985), and the elastic foundation's contact
    area by its small-contact closed form (a paraboloid on a foundation: F = pi K R* d^2 and the contact
    circle's area 2 pi R* d), within the articular mesh's discretisation."""
    from knee.models.contact import contact_along_flexion

    res = contact_along_flexion(volunteer, 700.0, flexion_deg=[10.0, 45.0, 90.0])
    st = solve_statics(volunteer, np.radians([10.0, 45.0, 90.0]), [0.0, 700.0, 0.0])
    E_star = 5.0 / (2 * (1 - 0.45 ** 2))
    K = 4.7414
    for name in ("lc", "mc"):
        lk = volunteer.params.link(name)
        c = res.contacts[name]
        np.testing.assert_allclose(c.force, np.maximum(-st.force(name), 0.0), rtol=1e-12)
        assert np.all(c.force > 100.0)  # a body-weight load is carried by both condyles
        sign = 1.0 if lk.tibia_surface == "convex" else -1.0
        R_star = 1.0 / (1.0 / lk.femur_radius + sign / lk.tibia_radius)
        a = (3 * c.force * R_star / (4 * E_star)) ** (1 / 3)
        np.testing.assert_allclose(c.hertz.area, np.pi * a ** 2, rtol=1e-9)
        np.testing.assert_allclose(c.hertz.peak, 3 * c.force / (2 * np.pi * a ** 2), rtol=1e-9)
        d = np.sqrt(c.force / (np.pi * K * R_star))
        np.testing.assert_allclose(c.foundation.area, 2 * np.pi * R_star * d, rtol=0.1)


@pytest.mark.parametrize("surface,rt", [("convex", 55.0), ("concave", 55.0)])
def test_tabulated_foundation_maps_match_the_root_solve(surface, rt):
    """The vectorised maps (force tabulated against approach, interpolated) agree with Brent's solve per load."""
    from knee.models.contact import foundation_maps

    cap = condyle_cap(24.0, subdivisions=5)
    loads = np.array([0.0, 150.0, 700.0, 1900.0])
    m = foundation_maps(loads, 24.0, rt, surface, mesh=cap)
    for k, F in enumerate(loads):
        r = foundation(F, 24.0, rt, surface, cap)
        assert m.approach[k] == pytest.approx(r.approach, rel=5e-3, abs=1e-9)
        assert m.peak[k] == pytest.approx(r.peak, rel=5e-3, abs=1e-9)
        net, _ = foundation_force(cap, 24.0, rt, surface, m.approach[k])
        assert net[2] == pytest.approx(F, rel=1e-2, abs=1e-9)
    with pytest.raises(KneeInputError, match="exceeds"):
        foundation_maps([1e7], 24.0, rt, surface, mesh=cap)
