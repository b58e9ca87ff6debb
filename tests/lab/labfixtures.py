"""The lab's tests (``lab/``): its labeler is registered for them, and only for them.

Importing ``lab`` registers its ``simulated-paper`` labeler into leap_core's registry. The product's tests
run in the same session and must see the product's labelers only (the CLI's help, the app's form, the
dataset check list what is registered), so the first import of this module (by the first lab test module
collected) takes the registration back, and :func:`lab_labeler`, which every lab test module uses
(``lab_labeler = labfixtures.lab_labeler``), registers the labeler for each test's span. (A module, not a
conftest.py: the tests import tests/conftest.py by its bare name, which a second conftest.py would take.)
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

import lab
from leap_core.labelers import LabelerSpec

lab.unregister()


@pytest.fixture(autouse=True)
def lab_labeler() -> Iterator[LabelerSpec[lab.SimulatedPaperConfig]]:
    """The lab's labeler, registered while the test runs."""
    lab.register()
    yield lab.LABELER
    lab.unregister()
