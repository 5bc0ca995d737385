"""Running a command so that file permissions apply to it, also when the tests run as root (in a container)."""

from __future__ import annotations

import os
import shutil


def without_dac(cmd: list[str]) -> list[str]:
    """Run ``cmd`` so that file permissions apply: as root, drop the capabilities that bypass them."""
    if os.geteuid() != 0:
        return cmd
    setpriv = shutil.which("setpriv")
    assert setpriv, "running the tests as root needs util-linux's setpriv"
    return [setpriv, "--inh-caps=-all", "--bounding-set=-dac_override,-dac_read_search"] + cmd
