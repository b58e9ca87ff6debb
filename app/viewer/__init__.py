"""The 3D review viewer (viser): see :mod:`app.viewer.session` for how the parts fit together.

Public surface: :class:`ViewerManager` (used by the app), :class:`ReviewSession` and its
:class:`ProjectBackend` protocol, :class:`ReviewScene` (the viser facade) and the pure view maths in
:mod:`app.viewer.view_logic`.
"""

from __future__ import annotations

from app.viewer.manager import AppBackend as AppBackend
from app.viewer.manager import ViewerInfo as ViewerInfo
from app.viewer.manager import ViewerManager as ViewerManager
from app.viewer.scene import ReviewScene as ReviewScene
from app.viewer.session import CorrectionRecord as CorrectionRecord
from app.viewer.session import ProjectBackend as ProjectBackend
from app.viewer.session import ReviewSession as ReviewSession
from app.viewer.session import RunInfo as RunInfo
from app.viewer.session import SessionConfig as SessionConfig

__all__ = [
    "AppBackend",
    "CorrectionRecord",
    "ProjectBackend",
    "ReviewScene",
    "ReviewSession",
    "RunInfo",
    "SessionConfig",
    "ViewerInfo",
    "ViewerManager",
]
