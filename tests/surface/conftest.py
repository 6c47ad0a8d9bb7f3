"""The surface tests reuse the synthetic scene of the dense tests."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "dense"))
