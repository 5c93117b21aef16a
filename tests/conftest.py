import os
from pathlib import Path

# Rerun switches its (viewer-only) analytics off on CI; the tests never start a viewer, and any
# `rerun` subprocess they run inherits this.
os.environ.setdefault("CI", "1")

import open3d  # noqa: E402
import pytest  # noqa: E402

# Open3D's registrations and distance queries sum over TBB threads in whatever order the threads finish, so
# two runs of a method on the same input differ in their last digits, and after a few hundred iterations by
# 0.002-0.075 mm at a node (one node 0.065 mm on a loaded two-core CI machine). Bounded to one thread they are
# bit-identical (measured on the reset test's runs, at the same time a run), so the tests that compare runs
# (a reset model against a fresh one, a fallback against a run without the failing phase) can ask for the same
# answer, not one within a tolerance that a real difference could hide in. The command keeps Open3D's threads.
open3d.utility.set_max_threads(1)


@pytest.fixture(scope="session")
def volunteer():
    from knee.models.mechanism import Mechanism

    return Mechanism.from_name("volunteer")


@pytest.fixture(scope="session")
def generic():
    from knee.models.mechanism import Mechanism

    return Mechanism.from_name("generic-sancisi2017")


#: The real, public knee data (../shared/data, README "Real data"): used where present, never copied.
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data():
    """The folder of real knee data, or a skip naming what is missing (a user's machine has none)."""
    if not (SHARED_DATA / "visible-human-male").is_dir():
        pytest.skip(f"real knee data not found at {SHARED_DATA} (see README, 'Real data')")
    return SHARED_DATA


@pytest.fixture(scope="session")
def visible_human(shared_data):
    from knee.fitting.reference_data import visible_human_knee

    return visible_human_knee(shared_data)


@pytest.fixture
def run_script():
    """``run_script(NAME, argv)``: ``scripts/NAME.py``'s main() run in this process with ``argv`` (sys.argv
    restored after); its exit code."""
    import importlib.util
    import sys

    def run(name: str, argv) -> int:
        path = Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(name, path)
        script = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(script)
        old = sys.argv
        sys.argv = [f"{name}.py", *map(str, argv)]
        try:
            return script.main()
        finally:
            sys.argv = old
    return run
