"""A command's --help (and the top level's) imports none of the heavy libraries: its start
stays well under the 0.3 s a user notices. Checked by the modules loaded, not by a clock."""

from __future__ import annotations

import subprocess
import sys

import pytest

from mocap.cli import COMMANDS

HEAVY = ("scipy", "cv2", "numba", "rerun", "av", "pyarrow", "matplotlib", "dask", "pycolmap", "ezc3d")

PROBE = """
import sys
from mocap.cli import build_parser
build_parser({command!r}).format_help()
print(" ".join(sorted({{name.split(".")[0] for name in sys.modules}} & set({heavy!r}))))
"""


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_help_imports_no_heavy_library(command):
    probe = PROBE.format(command=command or "", heavy=HEAVY)
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout
    assert out.split() == [], f"`mocap {command or ''} --help` imports {out.strip()}"


def test_shared_choices_match_the_libraries():
    from mocap.commands.arguments import DISTORTION_CHOICES
    from mocap.commands.synth import CODECS
    from mocap.reconstruct.refine import DISTORTION_CHOICES as REFINE_CHOICES
    from mocap.synthetic.encode import CODECS as ENCODER_CODECS

    assert set(DISTORTION_CHOICES) == set(REFINE_CHOICES)
    assert CODECS == ENCODER_CODECS
