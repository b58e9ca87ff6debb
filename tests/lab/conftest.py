"""The lab's tests (``lab/``): its labeler is registered for them, and only for them.

Importing ``lab`` registers its ``simulated-paper`` labeler into leap_core's registry. The product's tests
run in the same session and must see the product's labelers only (the CLI's help, the app's form, the
dataset check list what is registered), so this file, imported before the lab's test modules, takes the
registration back at once, and each lab test registers the labeler for its own span.
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
