"""``python -m lab ...``: the ``leap`` command line (``app.cli``) with the lab's labelers registered.

Every ``leap`` command and option works as in the product; ``--labeler`` also takes the lab's labelers and
``--labeler-preset`` their presets, and project files may name them::

    python -m lab run data/demo/sequences/00 --labeler simulated-paper --labeler-preset paper --out runs/paper
    python -m lab check data/demo/sequences/00 --labeler simulated-paper

It is the only module of the lab that imports ``app`` (the command line lives there); the product never
imports the lab.
"""

from __future__ import annotations

import lab
from app.cli import main

lab.register()  # explicit: the import above already did, this states why it is imported

if __name__ == "__main__":
    main()
