import os

# Rerun switches its (viewer-only) analytics off on CI; the tests never start a viewer, and any
# `rerun` subprocess they run inherits this.
os.environ.setdefault("CI", "1")

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def volunteer():
    from knee.models.mechanism import Mechanism

    return Mechanism.from_name("volunteer")


@pytest.fixture(scope="session")
def generic():
    from knee.models.mechanism import Mechanism

    return Mechanism.from_name("generic-sancisi2017")
