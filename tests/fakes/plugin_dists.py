"""Fake installed distributions for plugin-discovery tests: a folder on sys.path with ``NAME-VERSION.dist-info``
(METADATA, entry_points.txt in the ``teletouch`` group) and the plugin modules beside it, as pip would leave them.
The ``site`` fixture (tests/conftest.py) gives such a folder."""

from __future__ import annotations

from pathlib import Path


def make_dist(root: Path, dist: str, version: str, eps: dict[str, str], modules: dict[str, str]) -> None:
    """Install distribution ``dist`` into ``root``: entry points ``eps`` (name -> module) and ``modules`` (name ->
    source)."""
    info = root / f"{dist.replace('-', '_')}-{version}.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: {version}\n")
    (info / "entry_points.txt").write_text("[teletouch]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()))
    for mod, src in modules.items():
        (root / f"{mod}.py").write_text(src)



def estimator_source(name: str, prelude: str = "") -> str:
    """Source of a plugin module with one estimator ``name`` (output ``y``, 1.0 N) and its hook; ``prelude``: lines
    run before it (a print, an import that fails)."""
    return prelude + f'''
from teletouch import Component, Kind, Port, hookimpl

class C(Component):
    name = "{name}"
    kind = Kind.ESTIMATOR
    outputs = {{"y": Port("float64", (), "N")}}
    def step(self, t, inputs):
        return {{"y": 1.0}}

@hookimpl
def teletouch_components():
    return [C]
'''
