"""docs/writing-a-plugin.md as a newcomer uses it: every Python and YAML snippet on the page, laid out in a folder as
the page says (the component, its graph, its tests; the device of section 5 and its tests), runs as written."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAGE = REPO / "docs" / "writing-a-plugin.md"


def _blocks(section: str, lang: str) -> list[str]:
    """The ```lang code blocks of the page's section whose heading starts with ``section``."""
    text = PAGE.read_text()
    part = text.split(f"\n## {section}", 1)[1].split("\n## ", 1)[0]
    return re.findall(rf"```{lang}\n(.*?)```", part, flags=re.S)


def test_every_snippet_on_the_page_runs_as_written(tmp_path):
    (component,) = _blocks("1.", "python")
    (graph,) = _blocks("3.", "yaml")
    lowpass_tests = _blocks("4.", "python")[0]
    device, device_tests = _blocks("5.", "python")
    pkg = tmp_path / "teletouch_plugin_example"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(component)
    (tmp_path / "graph.yaml").write_text(graph)
    (tmp_path / "acme_gripper.py").write_text(device)
    tests = tmp_path / "tests"
    tests.mkdir()
    (tests / "test_lowpass.py").write_text(lowpass_tests)
    (tests / "test_acme_gripper.py").write_text(device_tests)
    env = {k: v for k, v in os.environ.items() if not k.startswith("TELETOUCH_")}
    env["PYTHONPATH"] = str(tmp_path)
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", str(tmp_path),
                        str(tests)], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "5 passed" in r.stdout, r.stdout


def test_the_device_on_the_page_loads_as_a_plugin(tmp_path, monkeypatch):
    """What `teletouch plugins` would say about section 5's device: it loads, with its ports and units."""
    (device, _) = _blocks("5.", "python")
    (tmp_path / "acme_gripper_doc.py").write_text(device)
    monkeypatch.syspath_prepend(str(tmp_path))
    from teletouch.testing import make_registry

    try:
        reg = make_registry("acme_gripper_doc", mocks=False)
        info = reg.components["acme-gripper"]
        assert info.cls.kind.value == "device"
        assert {n: p.unit for n, p in info.cls.outputs.items()} == {"opening": "m", "velocity": "m/s", "effort": "N"}
        # the upper bound the page recommends refuses millimetres typed as metres
        import pytest
        from pydantic import ValidationError

        with pytest.raises(ValidationError, match="initial_opening"):
            info.cls.Params(initial_opening=20)
        assert info.cls.Params(initial_opening="20mm").initial_opening == 0.02
    finally:
        sys.modules.pop("acme_gripper_doc", None)
