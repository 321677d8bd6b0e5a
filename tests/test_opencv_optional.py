"""OpenCV is an optional dependency (the ``opencv`` extra): the LAC leaderboard's environment
pins opencv-python, and a hard requirement on another OpenCV wheel would add a second cv2
(and, with opencv-python-headless 5.x, numpy 2). See docs/lac-environment.md."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from lunarloc.core.errors import DependencyError, import_cv2

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def _name(requirement: str) -> str:
    return re.split(r"[\s<>=!~;\[(]", requirement.strip(), maxsplit=1)[0].lower()


def test_no_opencv_wheel_is_a_hard_dependency():
    project = tomllib.loads(PYPROJECT.read_text())["project"]
    hard = [_name(r) for r in project["dependencies"]]
    assert "numpy" in hard  # the parse found the real list
    assert not [n for n in hard if n.startswith("opencv")]
    assert [_name(r) for r in project["optional-dependencies"]["opencv"]] == [
        "opencv-python-headless"
    ]


def test_missing_opencv_raises_the_install_hint(monkeypatch):
    from lunarloc.perception.images import normalize_image

    monkeypatch.setitem(sys.modules, "cv2", None)  # `import cv2` now raises ImportError
    with pytest.raises(DependencyError, match=r"lunarloc\[opencv\]"):
        import_cv2()
    with pytest.raises(DependencyError, match="opencv-python"):
        normalize_image(np.zeros((8, 8), np.uint8), "lift", sigma_px=2.0, gain=100.0)
