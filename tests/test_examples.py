"""The example scripts of ``tests/examples`` (run as a user would, through ``import knee``) and the README's
Python snippets, executed and pinned to numbers."""

import importlib.util
import math
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _example(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "tests" / "examples" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_example_mechanism_sweep():
    r = _example("mechanism_sweep").main()
    lo, hi = r["assembly_range_deg"]
    assert (lo, hi) == (pytest.approx(-103.79, abs=0.01), pytest.approx(129.29, abs=0.01))  # as in the README
    assert r["adduction_at_90_deg"] == pytest.approx(-6.343, abs=1e-3)
    assert r["internal_rotation_at_90_deg"] == pytest.approx(-17.608, abs=1e-3)
    assert r["anterior_at_90_mm"] == pytest.approx(-26.322, abs=1e-3)
    assert r["pf_flexion_at_90_deg"] == pytest.approx(68.674, abs=1e-3)
    assert r["max_residual_mm"] < 1e-9
    assert r["d_internal_rotation_d_acl_length"] == pytest.approx(6.94, abs=0.01)


def test_example_fit_synthetic_subject():
    r = _example("fit_synthetic_subject").main()
    assert r["frames"] == 60
    # the quick fit against the noise-free truth (seed 0): within the noise's reach, as measured
    for got, pinned in zip(r["tf_mae_vs_truth"], [0.45, 0.465, 0.129, 0.199, 0.221]):
        assert got == pytest.approx(pinned, abs=0.02)
    for got, pinned in zip(r["pf_mae_vs_truth"], [0.229, 0.602, 0.191, 0.113, 0.11, 0.155]):
        assert got == pytest.approx(pinned, abs=0.02)


def test_example_fem_with_prior():
    r = _example("fem_with_prior").main()
    # the demo subject's skin at 60 deg, made by the tetrahedral tissue (not the association model), seen
    # by the oblique camera: the method never sees more than that cloud
    assert r["points"] == 182807
    assert abs(r["flexion_error_deg"]) < 2.0  # measured -0.71 deg
    # its standard error from the method's two fits (the femur's placement, the tibia's correction): 1.32 deg
    # measured, the error within it, as in 83 % of the honest benchmark's views without skin mismatch
    assert r["flexion_sd_deg"] == pytest.approx(1.32, abs=0.05) and abs(r["flexion_error_deg"]) < r["flexion_sd_deg"]
    # the solver's refactorisations follow measured times: results agree to its tolerance, not bit for bit.
    # Pinned as measured on the tissue truth. The example's truth was the phantom's envelope of rigid capsules until the honest
    # benchmark's tissue truth replaced it; the FEM's choices that this benchmark favours lost there
    # (4.466 mm, 5.543 mm, the flexion 2.62 deg over on the last such build: BENCHMARKS.md). With the skin
    # pulled towards the points by springs from the points rather than from the skin (a one-sided view's skin
    # springs draw the leg towards the camera): 2.480 -> 1.506 mm, 2.292 -> 1.396 mm. With the femur's placement on
    # the posed skin paired with the skin itself rather than with samples of it: 1.506 -> 1.548 mm, 1.396 -> 1.448
    # mm, the tibia's correction 2.75 -> 2.80 deg, the flexion -1.18 -> -1.15 deg. With the tibia's turn about its
    # own axis given a 5 deg prior instead of 3: 1.548 -> 1.532 mm, 1.448 -> 1.436 mm, 2.80 -> 2.84 deg. With the
    # truth's skin refined with its spacing (its long faces bisected; the method unchanged): the cloud 182946 ->
    # 182807 points, 1.532 -> 1.448 mm, 1.436 -> 1.457 mm, 2.84 -> 3.12 deg, the flexion -1.15 -> -0.55 deg, the
    # mechanism alone 5.05 -> 4.64 mm. With the grid sized by the knee (8 x 7 on this phantom, the default; the
    # phantom's cases lose 0.05-0.08 mm on average on the honest benchmark, this one more): 1.448 -> 1.828 mm,
    # 1.457 -> 1.836 mm, 3.12 -> 3.19 deg, the flexion -0.55 -> -0.71 deg.
    assert r["footprints_mm"] == pytest.approx(1.828, abs=0.05)
    assert r["epiphysis_mm"] == pytest.approx(1.836, abs=0.05)
    assert r["tibia_correction_deg"] == pytest.approx(3.19, abs=0.1)
    # the FEM with the prior beats the mechanism alone (iv) on the same points (measured 4.64 mm)
    assert r["mechanism_alone_footprints_mm"] == pytest.approx(4.639, abs=0.05)
    assert r["footprints_mm"] < 0.6 * r["mechanism_alone_footprints_mm"]


def readme_snippets() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


@pytest.mark.parametrize("k", range(len(readme_snippets())))
def test_readme_python_snippets_run(k, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code = readme_snippets()[k]
    namespace = {"__name__": "__readme__"}
    exec(compile(code, f"README.md python block {k + 1}", "exec"), namespace)
    # each block states what it shows by the names it leaves; they are real numbers
    shown = {n: v for n, v in namespace.items() if n.startswith("result")}
    assert shown, "a README snippet should leave its result in a variable named result..."
    for v in shown.values():
        assert all(math.isfinite(float(x)) for x in _flatten(v))


def _flatten(v):
    try:
        import numpy as np

        return np.asarray(v, float).ravel()
    except (TypeError, ValueError):
        return [v]
