"""Real data that only this project's machines hold, outside the repository: the one place the
tests name it. A clone has none of it, and every test that reads it is marked ``shared_data`` and
skips, saying so.

machine-data: this project's machines keep real photo sets (LLFF fern, Strecha fountain-P11,
Tanks and Temples Family, ...) and the official VGGT fixture sets in a folder ``shared`` beside
the repository root; nothing in the repository depends on it.
"""
from __future__ import annotations

from pathlib import Path

#: real scenes, one folder per scene (``llff__fern``, ``strecha__fountain-P11``, ...)
SCENES = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "scenes"
#: the official VGGT's reference fixture sets (tests/data/vggt/shared is a committed copy of one)
VGGT_FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "vggt" / "fixtures"
#: the reason a test that needs them gives when it skips
ABSENT = "this project's machine data (real scenes, VGGT fixture sets) is not beside the repository"
